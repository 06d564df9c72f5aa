"""Body models: conventions, J24 mapping, gradients, fast paths, measurements, bad input."""

import math

import numpy as np
import pytest
import torch
from torch.autograd import gradcheck

from pressurepose.body import BodyParams, load_body_model
from pressurepose.body.joints import J24_MIRROR, J24_NAMES, joint_index
from pressurepose.body.params import all_finite, supine_rotation
from pressurepose.mat import MatSpec

J = {n: i for i, n in enumerate(J24_NAMES)}


@pytest.fixture(params=["anny", "smpl"])
def model(request, anny64, smpl64):
    return anny64 if request.param == "anny" else smpl64


def random_params(model, B=3, seed=0, pose_scale=0.4):
    g = torch.Generator().manual_seed(seed)
    shape = (
        torch.rand(B, model.shape_dim, generator=g, dtype=model.dtype) * 0.8 + 0.1
        if model.name == "anny"
        else torch.randn(B, model.shape_dim, generator=g, dtype=model.dtype)
    )
    return BodyParams(
        shape=shape,
        root_rotation=torch.randn(B, 3, generator=g, dtype=model.dtype) * 0.5,
        root_translation=torch.randn(B, 3, generator=g, dtype=model.dtype),
        pose=torch.randn(B, 23, 3, generator=g, dtype=model.dtype) * pose_scale,
    )


def supine_on_mat(model):
    mat = MatSpec()
    p = BodyParams.zeros(1, model.default_shape(1))
    top_of_head = model.rest_vertices(p.shape)[0, :, 1].max().item()  # body y = towards the head
    t = torch.tensor([[0.05 + top_of_head, mat.centre_m[1], 0.12]], dtype=model.dtype)
    return mat, p.replace(root_translation=t)


def test_supine_conventions(model):
    """docs/conventions.md: head over rows ~0-10, the subject's left hand towards +y (higher
    columns), feet towards the foot end, face up (+z)."""
    mat, p = supine_on_mat(model)
    out = model(p)
    rc = mat.to_taxel(out.joints[0, :, :2])
    assert 0 <= rc[J["head"], 0] <= 10
    assert rc[J["left_foot"], 0] > 55 and rc[J["right_foot"], 0] > 55
    centre_col = mat.cols / 2
    for side, sign in (("left", 1), ("right", -1)):
        for joint in ("hand", "wrist", "elbow", "shoulder", "hip", "knee", "ankle"):
            assert sign * (rc[J[f"{side}_{joint}"], 1] - centre_col) > 0, f"{side}_{joint}"
    assert out.joints[0, J["left_foot"], 2] > out.joints[0, J["left_ankle"], 2]  # toes up
    if model.name == "anny":  # the synthetic SMPL file's 'head' is a round cloud
        # The face is up: head vertices reach higher above the head joint than below it.
        head = out.vertices[0, out.part_labels == J["head"]]
        assert head[:, 2].max() - out.joints[0, J["head"], 2] > out.joints[0, J["head"], 2] - head[:, 2].min()


def test_root_translation_is_the_pelvis_and_zero_pose_is_a_t_pose(model):
    p = random_params(model, pose_scale=0.0).replace(root_rotation=torch.zeros(3, 3, dtype=model.dtype))
    j = model.joints(p)
    assert torch.allclose(j[:, 0], p.root_translation, atol=1e-12)
    if model.name != "anny":
        return  # SMPL's own rest pose is only roughly a T
    # T-pose: shoulder, elbow, wrist of each arm on one line across the bed (along y).
    for side in ("left", "right"):
        arm = j[:, [J[f"{side}_shoulder"], J[f"{side}_elbow"], J[f"{side}_wrist"]]]
        assert torch.allclose(arm[:, :, 0], arm[:, :1, 0].expand(-1, 3), atol=1e-9)
        assert torch.allclose(arm[:, :, 2], arm[:, :1, 2].expand(-1, 3), atol=1e-9)


def test_roll_pi_is_prone(model):
    _, p = supine_on_mat(model)
    prone = p.replace(root_rotation=torch.tensor([[math.pi, 0.0, 0.0]], dtype=model.dtype))
    a, b = model.joints(p)[0], model.joints(prone)[0]
    pelvis = p.root_translation[0]
    # Rolling about the bed axis through the pelvis: x kept, y and z mirrored.
    assert torch.allclose(b[:, 0], a[:, 0], atol=1e-9)
    assert torch.allclose(b[:, 1:] - pelvis[1:], -(a[:, 1:] - pelvis[1:]), atol=1e-9)


def test_mirrored_pose_gives_mirrored_body(model):
    p = random_params(model, B=2, seed=3)
    p = p.replace(
        shape=model.default_shape(2),
        root_rotation=torch.zeros(2, 3, dtype=model.dtype),
        root_translation=torch.zeros(2, 3, dtype=model.dtype),
    )
    mirror = torch.tensor(J24_MIRROR[1:]) - 1
    flip = torch.tensor([1.0, -1.0, -1.0], dtype=model.dtype)  # rotation vectors are pseudovectors
    pm = p.replace(pose=p.pose[:, mirror] * flip)
    a, b = model.joints(p), model.joints(pm)
    expected = a[:, list(J24_MIRROR)] * torch.tensor([1.0, -1.0, 1.0], dtype=model.dtype)
    tol = 2e-3 if model.name == "anny" else 1e-9  # Anny's mesh is symmetric to ~1 mm
    assert (b - expected).abs().max() < tol


def test_joints_fast_path_equals_full_forward(model):
    p = random_params(model, B=4, seed=5)
    out = model(p)
    assert out.vertices.shape == (4, model.num_vertices, 3) and out.joints.shape == (4, 24, 3)
    assert torch.allclose(model.joints(p), out.joints, atol=1e-10)


def test_outputs_are_consistent(model):
    out = model(random_params(model, B=1))
    V = model.num_vertices
    assert out.faces.dtype == torch.int64 and out.faces.max() < V and out.faces.min() >= 0
    assert out.part_labels.shape == (V,) and out.part_labels.max() < 24
    assert out.skinning_weights.shape == (V, 24)
    assert torch.allclose(out.skinning_weights.sum(-1), torch.ones(V, dtype=model.dtype), atol=1e-6)
    assert set(out.part_labels.unique().tolist()) >= {J["head"], J["left_knee"], J["right_elbow"]}


def test_gradcheck_float64(model):
    """Exact gradients w.r.t. shape, pose and root, through joints and vertices."""
    p = random_params(model, B=1, seed=7)
    g = torch.Generator().manual_seed(0)
    w_vertices = torch.randn(model.num_vertices, 3, generator=g, dtype=torch.float64)
    w_joints = torch.randn(24, 3, generator=g, dtype=torch.float64)

    def f(shape, root_rotation, pose):
        q = p.replace(shape=shape, root_rotation=root_rotation, pose=pose)
        out = model(q)
        return (out.vertices[0] * w_vertices).sum() + (model.joints(q)[0] * w_joints).sum()

    inputs = tuple(t.clone().requires_grad_() for t in (p.shape, p.root_rotation, p.pose))
    assert gradcheck(f, inputs, eps=1e-6, atol=1e-5, fast_mode=True)


def test_float32_matches_float64(anny32, anny64):
    p = random_params(anny64, B=2, seed=11)
    a = anny64(p)
    b = anny32(p.to(torch.float32))
    assert (a.vertices - b.vertices.double()).abs().max() < 1e-4


def test_anny_native_rest_pose_reproduces_anny(anny64):
    """The T-pose bridge is exact: the pose that undoes it gives Anny's own A-pose mesh."""
    shape = torch.tensor([[0.1, 0.8, 0.3, 0.9, 0.2, 0.6]], dtype=torch.float64)
    pose = anny64.native_rest_pose(shape)
    # A-pose: upper arms ~45-50 deg below horizontal (left shoulder pitch about z < 0).
    assert -55 < math.degrees(pose[0, J["left_shoulder"] - 1, 2]) < -40
    p = BodyParams.zeros(1, shape).replace(pose=pose)
    out = anny64(p)
    native = anny64.anny(None, phenotype_kwargs=shape)
    C = anny64.c_smpl_to_anny
    v = native["vertices"] @ C  # Anny axes -> body axes; the root sits at the origin
    v = v @ supine_rotation(torch.float64).T  # zero root rotation = the supine reference
    assert (out.vertices - v).abs().max() < 1e-9


def test_measurements_are_plausible_and_monotone(anny64):
    s = anny64.shape_from_dict
    base = anny64.measure(anny64.default_shape(1))
    assert 1.6 < base.height_m.item() < 2.0
    assert 55 < base.mass_kg.item() < 95
    assert base.mass_kg.item() == pytest.approx(base.volume_m3.item() * 980.0)
    heavy = anny64.measure(s({"weight": 0.9}))
    tall = anny64.measure(s({"height": 0.9}))
    assert heavy.mass_kg > base.mass_kg + 5
    assert tall.height_m > base.height_m + 0.05
    # A closed mesh with outward faces has a positive signed volume.
    assert base.volume_m3.item() > 0


def test_measure_is_differentiable(anny64):
    shape = anny64.default_shape(1).requires_grad_()
    anny64.measure(shape).mass_kg.sum().backward()
    assert shape.grad[0, 3] > 0  # more 'weight' phenotype -> more mass


# --- bad input ----------------------------------------------------------------------------
def test_bad_shapes_dtypes_and_nan(anny32):
    p = BodyParams.zeros(2, anny32.default_shape(2))
    with pytest.raises(ValueError, match=r"BodyParams.pose must have shape \(B, 23, 3\), got \(2, 24, 3\)"):
        anny32(p.replace(pose=torch.zeros(2, 24, 3)))
    with pytest.raises(ValueError, match=r"BodyParams.shape must have shape \(B, 6\)"):
        anny32(p.replace(shape=torch.zeros(2, 10)))
    with pytest.raises(ValueError, match="batch size 3"):
        anny32(p.replace(root_translation=torch.zeros(3, 3)))
    with pytest.raises(ValueError, match="dtype torch.float64, but the body model is torch.float32"):
        anny32(p.to(torch.float64))
    bad = p.pose.clone()
    bad[0, 3, 1] = float("nan")
    with pytest.raises(ValueError, match="BodyParams.pose contains NaN"):
        anny32.joints(p.replace(pose=bad))
    with pytest.raises(ValueError, match="expected BodyParams"):
        anny32({"pose": p.pose})
    # infinities, in the parameters and in the shape; finite values whose sum overflows pass
    for field, value in (("root_translation", float("inf")), ("root_rotation", -float("inf"))):
        bad = getattr(p, field).clone()
        bad[1, 2] = value
        with pytest.raises(ValueError, match=f"BodyParams.{field} contains NaN or infinite"):
            anny32.joints(p.replace(**{field: bad}))
    with pytest.raises(ValueError, match="shape \\(Anny phenotypes\\) contains NaN or infinite"):
        anny32.validate_shape(torch.tensor([[0.5, float("nan"), 0.5, 0.5, 0.5, 0.5]]))
    huge = torch.full((2, 3), 3e38)
    assert all_finite(huge) and not math.isfinite(huge.sum())
    assert not all_finite(torch.tensor([1.0, float("nan")])) and not all_finite(torch.tensor([float("inf")]))


def test_bad_phenotypes(anny32):
    with pytest.raises(ValueError, match=r"unknown phenotype name\(s\) \['bmi'\]"):
        anny32.shape_from_dict({"bmi": 0.3})
    shape = anny32.default_shape(1)
    shape[0, 4] = 1.5
    with pytest.raises(ValueError, match=r"must lie in \[0, 1\]; height out of range"):
        anny32(BodyParams.zeros(1, shape))


def test_unknown_names():
    with pytest.raises(ValueError, match="unknown joint name 'elbow'"):
        joint_index("elbow")
    with pytest.raises(ValueError, match="unknown body backend 'star'"):
        load_body_model("star")


def test_j24_tables():
    assert len(J24_NAMES) == 24 and J24_NAMES[0] == "pelvis" and J24_NAMES[15] == "head"
    assert J24_MIRROR[J["left_hand"]] == J["right_hand"] and J24_MIRROR[J["neck"]] == J["neck"]
    assert all(J24_MIRROR[J24_MIRROR[i]] == i for i in range(24))
    assert np.all(np.diff([J["left_hip"], J["left_knee"], J["left_ankle"], J["left_foot"]]) > 0)


@pytest.mark.gpu
@pytest.mark.parametrize("backend", ["anny", "smpl"])
def test_cuda_matches_cpu(backend, smpl_dir):
    options = {"model_dir": smpl_dir} if backend == "smpl" else {}
    cpu = load_body_model(backend, dtype=torch.float64, **options)
    gpu = load_body_model(backend, dtype=torch.float64, device="cuda", **options)
    p = random_params(cpu, B=3, seed=13)
    a, b = cpu(p), gpu(p.to("cuda"))
    assert (a.vertices - b.vertices.cpu()).abs().max() < 1e-9
    assert (cpu.joints(p) - gpu.joints(p.to("cuda")).cpu()).abs().max() < 1e-9


def test_each_backend_says_what_its_shape_means(model):
    # The members capsules, fit_shape and the sampler use instead of branching on the name.
    S = model.shape_dim
    female = torch.tensor([1.0, 0.0, 0.5], dtype=model.dtype)
    average = model.average_shape(female)
    assert average.shape == (3, S) and average.dtype == model.dtype
    model.validate_shape(average)
    if "gender" in model.shape_names:  # Anny: the gender is a shape entry
        assert model.fixed_gender is None
        assert torch.equal(model.female_fraction(average), female)
        others = [i for i, n in enumerate(model.shape_names) if n != "gender"]
        assert torch.equal(average[:, others], model.default_shape(3)[:, others])
    else:  # SMPL: the file's gender (the test file is the neutral one)
        assert model.fixed_gender is None and model.gender == "neutral"
        assert torch.equal(average, model.default_shape(3))
        assert torch.equal(model.female_fraction(average), torch.full((3,), 0.5, dtype=model.dtype))
    for gender in ("female", "male"):
        low, high = type(model).shape_bounds(gender, model.shape_names)
        assert low.shape == high.shape == (S,) and (low <= high).all()
    # with_size: only the size entries move, within bounds, and z = 0 is the middle.
    z = torch.tensor([[0.0] * model.size_dim, [4.0] * model.size_dim, [-4.0] * model.size_dim], dtype=model.dtype)
    sized = model.with_size(average, z)
    moved = (sized != average).any(0)
    assert 1 <= int(moved.sum()) == model.size_dim
    model.validate_shape(sized)
    lo, hi = sized[2, moved], sized[1, moved]
    assert torch.allclose(sized[0, moved], (lo + hi) / 2, atol=1e-12) and (lo < hi).all()


def test_anny_size_entries_make_taller_heavier_bodies(anny64):
    base = anny64.average_shape(torch.tensor([0.0, 0.0], dtype=torch.float64))
    sized = anny64.with_size(base, torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=torch.float64))
    m = anny64.measure(sized)
    assert m.height_m[1] > m.height_m[0] + 0.1 and m.mass_kg[1] > m.mass_kg[0] + 10


def test_a_gendered_smpl_file_refuses_the_other_gender(smpl_dir, tmp_path):
    import shutil

    from pressurepose.errors import UserError
    from pressurepose.sampling.partitions import SamplingConfig
    from pressurepose.sampling.sampler import PoseSampler

    shutil.copy(smpl_dir / "SMPL_NEUTRAL.npz", tmp_path / "SMPL_FEMALE.npz")
    female = load_body_model("smpl", model_dir=tmp_path, gender="female", dtype=torch.float64)
    assert female.fixed_gender == "female"
    assert torch.equal(female.female_fraction(female.default_shape(2)), torch.ones(2, dtype=torch.float64))
    with pytest.raises(UserError, match="smpl body model is female but the sampling asks for male"):
        PoseSampler(female, SamplingConfig(partition="supine", gender="male"))
    PoseSampler(female, SamplingConfig(partition="supine", gender="female"))  # accepted


def test_anny_inference_path_matches_the_differentiable_one(anny64):
    """Without autograd Anny poses the mesh by blocked skinning (axes, root rotation and
    translation folded into the bone transforms) and reuses the last shapes' skeleton pass:
    the same vertices and joints as the differentiable path, for new shapes too."""
    from pressurepose.body.anny_skinning import BlockedSkinning

    for seed in (0, 1):
        p = random_params(anny64, B=3, seed=seed)
        wanting = BodyParams(
            shape=p.shape.clone().requires_grad_(True),
            root_rotation=p.root_rotation,
            root_translation=p.root_translation,
            pose=p.pose,
        )
        ref = anny64(wanting)
        assert ref.vertices.requires_grad  # the differentiable path
        with torch.inference_mode():
            out = anny64(p)
            joints = anny64.joints(p)
            rest = anny64.rest_vertices(p.shape)
        torch.testing.assert_close(out.vertices, ref.vertices.detach(), atol=1e-10, rtol=0)
        torch.testing.assert_close(out.joints, ref.joints.detach(), atol=1e-12, rtol=0)
        torch.testing.assert_close(joints, ref.joints.detach(), atol=1e-12, rtol=0)
        torch.testing.assert_close(rest, anny64.rest_vertices(wanting.shape).detach(), atol=1e-12, rtol=0)
    # blocks of any size give the same mesh as one block
    skin = BlockedSkinning(anny64.anny.template_vertices, anny64.anny.blendshapes, anny64.skin_matrix)
    coeffs = anny64._coefficients(p.shape)
    T = torch.linalg.qr(torch.randn(3, skin.num_bones, 3, 3, dtype=torch.float64))[0]
    t = torch.randn(3, skin.num_bones, 3, dtype=torch.float64)
    whole = skin.pose(coeffs, T, t)
    import pressurepose.body.anny_skinning as mod

    old, mod.BLOCK_FLOATS = mod.BLOCK_FLOATS, 1000
    try:
        blocked = BlockedSkinning(anny64.anny.template_vertices, anny64.anny.blendshapes, anny64.skin_matrix)
        assert len(blocked._rows(3)) > 10
        torch.testing.assert_close(blocked.pose(coeffs, T, t), whole, atol=1e-12, rtol=0)
    finally:
        mod.BLOCK_FLOATS = old
    with pytest.raises(ValueError, match="expected T"):
        skin.pose(coeffs, T[:, :5], t)


def test_blocked_skinning_from_the_transposed_basis_matches_row_by_row(anny64):
    """Batches of TRANSPOSED_FROM bodies or more take the rest vertices from a transposed copy
    of the blendshapes: each body's mesh is the one it gets posed alone."""
    from pressurepose.body.anny_skinning import TRANSPOSED_FROM, BlockedSkinning

    B = TRANSPOSED_FROM + 1
    g = torch.Generator().manual_seed(6)
    skin = BlockedSkinning(anny64.anny.template_vertices, anny64.anny.blendshapes, anny64.skin_matrix)
    coeffs = anny64._coefficients(torch.rand(B, 6, dtype=torch.float64, generator=g))
    T = torch.linalg.qr(torch.randn(B, skin.num_bones, 3, 3, dtype=torch.float64, generator=g))[0]
    t = torch.randn(B, skin.num_bones, 3, dtype=torch.float64, generator=g)
    batch = skin.pose(coeffs, T, t)
    assert skin._basis_t is not None  # the transposed path ran
    alone = torch.cat([skin.pose(coeffs[i : i + 1], T[i : i + 1], t[i : i + 1]) for i in range(B)])
    torch.testing.assert_close(batch, alone, atol=1e-12, rtol=0)


def test_anny_rest_joints_without_kinematics_match_the_posing(anny64):
    """Anny's closed-form T-pose joints (chains of T-pose corrections) equal the joints of
    the zero pose posed level by level, with and without autograd."""
    from pressurepose.body.model import BodyModel

    shape = torch.rand(3, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    reference = BodyModel.rest_joints(anny64, shape)
    torch.testing.assert_close(anny64.rest_joints(shape), reference, atol=1e-12, rtol=0)
    with torch.inference_mode():
        torch.testing.assert_close(anny64.rest_joints(shape), reference, atol=1e-12, rtol=0)
    wanting = shape.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(anny64.rest_joints(wanting)[:, 20].sum(), wanting)
    (g_ref,) = torch.autograd.grad(BodyModel.rest_joints(anny64, wanting)[:, 20].sum(), wanting)
    torch.testing.assert_close(g, g_ref)


def test_anny_kept_shape_pass_never_meets_autograd(anny64):
    """The skeleton pass Anny keeps from an inference call is not reused when grad mode is on:
    a pose that wants gradients, on the same shapes, still differentiates."""
    p = random_params(anny64, B=2, seed=4)
    with torch.inference_mode():
        anny64(p)  # keeps these shapes' skeleton pass (inference tensors)
    pose = p.pose.clone().requires_grad_(True)
    wanting = BodyParams(shape=p.shape, root_rotation=p.root_rotation, root_translation=p.root_translation, pose=pose)
    (g,) = torch.autograd.grad(anny64.joints(wanting).sum() + anny64(wanting).vertices.sum(), pose)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_anny_copies_and_pickles_after_inference(anny32):
    """The inference caches (kept skeleton pass, skinning blocks) are left out of copies and
    pickles: a copy made after inference calls poses the same mesh."""
    import copy
    import pickle

    p = random_params(anny32, B=2, seed=5)
    with torch.inference_mode():
        before = anny32(p).vertices
        anny32.rest_joints(p.shape)
    for twin in (copy.deepcopy(anny32), pickle.loads(pickle.dumps(anny32))):
        assert "_blocked" not in twin.__dict__ and "_shape_memo" not in twin.__dict__
        with torch.inference_mode():
            torch.testing.assert_close(twin(p).vertices, before)


def test_nearest_rotation_matches_roma_on_anny_and_random_matrices(anny32):
    """The elementwise special Procrustes (Anny's rest bone orientations without autograd) gives
    roma's rotations: to float64 round-off, and the same float32 numbers on Anny's matrices;
    with autograd it is roma's."""
    import roma

    from pressurepose.body.procrustes import nearest_rotation

    g = torch.Generator().manual_seed(7)
    m = anny32.anny
    coeffs = anny32._coefficients(torch.rand(128, 6, generator=g))
    M = m.bone_template_orientation_matrices + torch.einsum("ba,akij->bkij", coeffs, m.bone_orientation_blendshapes)
    M = M[:, 1:]
    assert (torch.linalg.det(M) < 0).any()  # both signs of det occur
    with torch.no_grad():
        assert torch.equal(nearest_rotation(M), roma.special_procrustes(M))
        X = torch.randn(2000, 3, 3, dtype=torch.float64, generator=g)
        R = nearest_rotation(X)
        torch.testing.assert_close(R, roma.special_procrustes(X), atol=1e-11, rtol=0)
        torch.testing.assert_close(torch.linalg.det(R), torch.ones(2000, dtype=torch.float64))
        zero = nearest_rotation(torch.zeros(1, 3, 3, dtype=torch.float64))
        torch.testing.assert_close(zero, torch.eye(3, dtype=torch.float64)[None])
        # a nearly ambiguous matrix (two equal singular values, det < 0) is left to roma
        tie = torch.diag(torch.tensor([1.0, 0.5, -0.5], dtype=torch.float64))[None]
        assert torch.equal(nearest_rotation(tie), roma.special_procrustes(tie))
    wanting = torch.randn(3, 3, 3, dtype=torch.float64, generator=g).requires_grad_(True)
    (grad,) = torch.autograd.grad(nearest_rotation(wanting).sum(), wanting)
    assert torch.isfinite(grad).all()
