"""Exact nearest-neighbour search (eval.nearest, k-d trees) against the brute force: random
clouds of many shapes and sizes, body meshes, several pairs of sets at once, and bad input."""

import pytest
import torch

from pressurepose.body.params import BodyParams
from pressurepose.eval.metrics import camera_facing
from pressurepose.eval.nearest import PointSets, nearest_brute, nearest_distance, nearest_pairs

D = torch.float64


def brute_two_way(a, b):
    return nearest_brute(a, b), nearest_brute(b, a)


def clouds(seed: int):
    """Point sets of awkward sizes and shapes (float64): solid, flat, on a line, duplicated,
    far apart, a single point."""
    g = torch.Generator().manual_seed(seed)
    cube = torch.rand(1000, 3, generator=g, dtype=D)
    flat = torch.rand(700, 3, generator=g, dtype=D) * torch.tensor([1.7, 0.5, 0.0], dtype=D)  # no z extent
    line = torch.rand(90, 1, generator=g, dtype=D) * torch.tensor([[0.0, 1.0, 0.2]], dtype=D)  # no x extent
    dup = torch.rand(40, 3, generator=g, dtype=D).repeat(3, 1)  # every point three times
    far = torch.rand(33, 3, generator=g, dtype=D) + 10.0
    one = torch.rand(1, 3, generator=g, dtype=D)
    return [cube, flat, line, dup, far, one, cube[:32], cube[:31]]


@pytest.mark.parametrize("seed", [0, 1])
def test_every_pair_of_sets_matches_the_brute_force(seed):
    sets = clouds(seed)
    packed = PointSets(sets)
    pairs = [(i, j) for i in range(len(sets)) for j in range(len(sets))]
    for (i, j), (to_b, to_a) in zip(pairs, nearest_pairs(packed, packed, pairs)):
        want_b, want_a = brute_two_way(sets[i], sets[j])
        assert to_b.shape == want_b.shape and to_a.shape == want_a.shape
        assert float((to_b - want_b).abs().max()) <= 1e-9, (i, j)
        assert float((to_a - want_a).abs().max()) <= 1e-9, (i, j)


def test_identical_sets_give_exactly_zero_and_shifts_their_length():
    g = torch.Generator().manual_seed(3)
    pts = torch.rand(2000, 3, generator=g, dtype=D)
    assert float(nearest_distance(pts, pts).abs().max()) == 0.0
    assert float(nearest_distance(pts.float(), pts.float()).abs().max()) == 0.0
    # A far shift moves every nearest neighbour by the shift (the set keeps its order).
    shift = torch.tensor([0.0, 0.0, 5.0], dtype=D)
    flat = pts * torch.tensor([1.0, 1.0, 0.0], dtype=D)
    torch.testing.assert_close(nearest_distance(flat + shift, flat), torch.full((2000,), 5.0, dtype=D))


def test_body_meshes_match_the_brute_force(anny64):
    """The use 3DVPE makes of it: camera-facing vertices of two posed bodies ~cm apart, and
    of two bodies far apart (a poor estimate)."""
    g = torch.Generator().manual_seed(4)
    params = BodyParams.zeros(3, anny64.default_shape(3), dtype=D)
    params = params.replace(
        pose=0.3 * torch.randn(3, 23, 3, generator=g, dtype=D),
        root_translation=torch.tensor([[1.0, 0.4, 0.2], [1.02, 0.41, 0.21], [1.3, 0.3, 0.25]], dtype=D),
    )
    verts = anny64(params).vertices
    mask, _ = camera_facing(verts, anny64.faces)
    sets = [verts[k][mask[k]] for k in range(3)]
    packed = PointSets(sets)
    pairs = [(0, 1), (0, 2), (2, 1)]
    for (i, j), (to_b, to_a) in zip(pairs, nearest_pairs(packed, packed, pairs)):
        want_b, want_a = brute_two_way(sets[i], sets[j])
        assert float((to_b - want_b).abs().max()) <= 1e-9 and float((to_a - want_a).abs().max()) <= 1e-9
    # float32 (what evaluate runs in): the brute force's |p|^2 - 2 q.p choice is itself only
    # round-off accurate, so agreement is to round-off.
    a, b = sets[0].float(), sets[1].float()
    torch.testing.assert_close(nearest_distance(a, b), nearest_brute(a, b), rtol=0, atol=5e-5)
    torch.testing.assert_close(
        nearest_distance(a, b).double(), nearest_brute(a.double(), b.double()), rtol=0, atol=1e-6
    )


def test_distances_come_back_in_the_sets_dtype():
    pts = torch.rand(50, 3, dtype=D)
    assert nearest_distance(pts.float(), pts.float()).dtype == torch.float32
    assert nearest_distance(pts, pts).dtype == D


def test_bad_inputs_are_refused():
    pts = torch.rand(10, 3, dtype=D)
    with pytest.raises(ValueError, match=r"point set 1 must have shape \(N, 3\) with N >= 1"):
        PointSets([pts, pts[:0]])
    with pytest.raises(ValueError, match="shape"):
        PointSets([pts[:, :2]])
    with pytest.raises(ValueError, match="NaN"):
        PointSets([torch.full((3, 3), float("nan"))])
    with pytest.raises(IndexError):
        nearest_pairs(PointSets([pts]), PointSets([pts]), [(0, 1)])
    assert nearest_pairs(PointSets([pts]), PointSets([pts]), []) == []
