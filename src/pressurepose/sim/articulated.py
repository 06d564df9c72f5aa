"""Sim #2, articulated: the posed mesh comes to static rest segment by segment.

The rigid rest (`foundation.simulate_pressure`) moves the whole mesh as one body, so only its
lowest regions touch the bed. Here every J24 part of the mesh (the vertices its skinning
assigns to a joint) carries its own weight through its own contact, and the joints between
parts are compliant: each is a rotational spring with sim #1's stiffness (seed A.2, scaled by
the body's mass) about the pose it starts in. A calf, a forearm or the head that hangs above
the foam sinks onto it until the spring and the foam hold its weight.

Mechanics (docs/physics.md, "articulated rest"): unknowns q per body are the vertical shift
dz, and small rotations theta_k about horizontal axes u_k through joint pivots p_k (the root:
roll and pitch about the centre of mass; ball joints: the bed's x and y axes; knees and
elbows: their hinge axis). A rotation moves the joint's whole subtree; to first order a
point r of the subtree rises by theta_k (u_k x (r - p_k))_z, which is affine in the point's
(x, y): a_k . (1, x, y). The resting state minimises the potential energy

    E(q) = sum_parts m_s g z_s(q) + sum_k 1/2 k_k (e_k + theta_k)^2 + sum_cells A Phi(w_i(q))

(gravity, joint springs with e_k the deflection already in the joint, the stored energy Phi
of the foam and the soft tissue in series per unit area, `soft_contact.series_law`), with w_i the compression of grid cell i
under its lowest surface point. With the cells' heights linearised the problem is convex:
Newton with a backtracking line search on E, the Hessian assembled from per-part moments of
the contact stiffness (sum c (1, x, y)(1, x, y)^T) summed over subtrees, so a step costs one
pass over the cells and a (N x N) solve, N = 45. Re-posings apply the motion exactly to the
pose parameters (the parts riding their joints rigidly in between) and re-linearise; knee and
elbow limits are stiff one-sided springs in the energy; the last solve's field is the pressure
(force balances the weight to solver tolerance); the mesh is skinned once at the end. The early
re-posings only bring the body near its rest: they find the contacts on a coarse grid (one cell
per taxel, the mesh's vertices only, `sim.contact_grid`), the last ones and the rest on the
image's grid with every surface point.

Batched over B bodies, float64, CPU or CUDA; on a flat bed or one whose head section is raised
(`sim.raised`: each section's cells in its own frame).
"""

from __future__ import annotations

import dataclasses

import torch

from pressurepose.bed import BedShape
from pressurepose.body.capsules import fit_capsules
from pressurepose.body.kinematics import pose_in_mat, rest_joints
from pressurepose.body.model import BodyModel
from pressurepose.body.params import BodyParams, root_matrix, root_roll
from pressurepose.body.rotations import matrix_to_axis_angle
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sim.articulated_config import ArticulatedConfig
from pressurepose.sim.articulation import (
    Dofs,
    apply_motion,
    corner_mass_and_com,
    dof_axes_pivots,
    dof_geometry,
    joint_stiffness,
    lying_reference,
    tissue_modulus,
    tissue_sag,
    to_part_frames,
)
from pressurepose.sim.contact_grid import ContactGrid
from pressurepose.sim.foundation import FAIL_BOTTOM, FAIL_SLIDES
from pressurepose.sim.friction import Friction
from pressurepose.sim.linearised import Linearised, minimise
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams
from pressurepose.sim.pillow import footprint, spread_load
from pressurepose.sim.raised import RaisedBed, on_sheet
from pressurepose.sim.rest_setup import SurfaceLayout
from pressurepose.sim.rest_state import FAIL_TILT, MovingBodies, RestsDone, damp_swings
from pressurepose.sim.self_contact import SelfContact
from pressurepose.sim.wedge import rigid_base, wedge_thickness

# The revision of the engine's numerics: raised whenever a change alters its rests beyond
# bitwise (datasets pin it, `generate.run`). 2: stalled solves leave, trimmed cells, a
# re-posing's solve stops at 1 mrad steps (docs/benchmarks.md, branch speed4); 3: the body
# model's rest skeleton by `body.procrustes.nearest_rotation` (roma's numbers to round-off,
# branch pred6), which the rests amplify beyond bitwise; 4: the thorax's tissue depth at most
# `ArticulatedConfig.tissue_depth_max` (the ribcage, docs/realism.md "The ribcage"); 5: at most
# 20 re-posings instead of 14 (`ArticulatedConfig.outer`, session 42, docs/realism.md); 6: the
# rests unchanged, but the datasets' settle_steps column carries each body's re-posings (outer + 1
# for a body still moving at the cap, `ArticulatedRest.settled`; session 43); 7: a swinging
# unknown takes a secant share of its re-posing's motion (`ArticulatedConfig.damp_swings`,
# session 46); 8: raised beds rest articulated too (`sim.raised`, session 46; flat beds as in 7);
# 9: the re-posings before the last 8 find their contacts on a taxel-sized grid with the mesh's
# vertices only, 3 Newton steps each, and 24 re-posings at most (`ArticulatedConfig.coarse_sub`,
# session 49, docs/physics.md "Two grids"); 10: the body model's rotations, forward kinematics and
# Anny's phenotype coefficients written for speed (session 57, docs/benchmarks.md; the same
# numbers to round-off, which the rests amplify beyond bitwise, as in 3).
ENGINE_REVISION = 10


@dataclasses.dataclass
class ArticulatedRest:
    """B bodies at articulated rest. Pressures in Pa on the covered grid (cells), before the
    mat/cover and the sensor."""

    params: BodyParams  # the pose at rest
    vertices: torch.Tensor  # (B, V, 3) mesh at rest (mat frame, m)
    joints: torch.Tensor  # (B, 24, 3)
    # (B, rows*sub, cols*sub) pressure per cell on the mattress top (under a pillow: at its base)
    foundation_pa: torch.Tensor
    force_n: torch.Tensor  # (B,) the force holding the weight (on a raised bed the normals' vertical resultant)
    max_compression_m: torch.Tensor  # (B,) deepest compression of the foam
    part_force_n: torch.Tensor  # (B, 24) contact (normal) force carried by each J24 part
    self_penetration_m: torch.Tensor  # (B,) deepest overlap of the capsule pairs that started apart
    iterations: torch.Tensor  # (B,) Newton steps
    reposings: torch.Tensor  # (B,) re-posings each body took (ArticulatedConfig.outer at most)
    # (B,) False: the last re-posing still moved the body (the motion it took - swing damping's
    # share of its linearisation's - beyond the settled_* tolerances):
    # the cap, not its balance, ended its rest; its image is its last linearisation's balance
    settled: torch.Tensor
    failure: list[str]
    sub: int
    pillow_m: torch.Tensor | None = None  # (B,) the pillows' free thickness (0: none), or None
    # (B,) on a raised bed: the push toward the foot of the raised section's normal forces over
    # the total normal force - the sheet's friction ratio the rest needs (`sim.raised`); else None
    friction_ratio: torch.Tensor | None = None


# A hinge pushed beyond its limit meets a spring this many times its own stiffness.
_LIMIT_STIFFNESS_RATIO = 100.0


def rest_articulated(
    model: BodyModel,
    params: BodyParams,
    mass_kg: torch.Tensor | None = None,
    mattress: MattressParams | None = None,
    mat: MatSpec | None = None,
    config: ArticulatedConfig | None = None,
    pillow_m: torch.Tensor | None = None,
    bed: BedShape | None = None,
) -> ArticulatedRest:
    """Rest B posed bodies (BodyParams, float64 model) on the mattress, every part on its
    own contact with compliant joints (module doc). The bodies may start above the bed or in
    it; their horizontal placement and yaw are kept. Failures are reported per sample.
    `pillow_m` (B,): each body's head on a pillow of this free thickness (m; 0: none;
    `ArticulatedConfig.pillow` its size and material, `sim.pillow`). `bed`: a raised head
    section (`sim.raised`; default flat): pressures normal to each section, on the mat's grid in
    surface coordinates."""
    mp = mattress or MattressParams()
    mat = mat or MatSpec()
    raised = None if bed is None or bed.flat else RaisedBed(bed, mat, model.dtype, model.device)
    cfg = config or ArticulatedConfig()
    dtype, device = model.dtype, model.device
    B = params.batch_size
    dofs = Dofs(device, dtype)
    # Surface points (vertices, then triangle centroids) sorted by part, so each part is a
    # contiguous slice when the parts are moved.
    layout = SurfaceLayout.build(model.faces, model.part_labels)
    labels = layout.labels
    fine = ContactGrid.build(mat, mp, cfg.sub, raised, dtype, device)
    coarse = None
    n_coarse = cfg.coarse_reposings
    if n_coarse:
        coarse = ContactGrid.build(mat, mp, cfg.coarse_sub, raised, dtype, device)
    X, Y, xy, area = fine.X, fine.Y, fine.xy, fine.area
    # A pose may start beyond a limit (the sampler's ranges are not the limits'): the limit
    # then sits where the joint starts, so the spring stops it going further, never pushes.
    dof_lo, dof_hi = dofs.limits(dtype, device)
    start_angle = dofs.hinge_angles(params.pose)
    dof_lo = torch.minimum(dof_lo[None], start_angle)
    dof_hi = torch.maximum(dof_hi[None], start_angle)
    rest = rest_joints(model, params.shape)
    out = model(params)
    total_mass = (
        model.measure(params.shape).mass_kg
        if mass_kg is None
        else torch.as_tensor(mass_kg, dtype=dtype, device=device).reshape(-1)
    )
    weight = total_mass * GRAVITY_M_S2
    k = joint_stiffness(
        total_mass,
        dofs,
        cfg.stiffness_scale,
        cfg.neck_stiffness_scale,
        cfg.spine_stiffness_scale,
        cfg.spine_lateral_scale,
        root_roll(params.root_rotation),
    )
    # The trunk's roll hold (a person's muscle tone on a side; sim #1's SettleConfig.hold_roll_m):
    # a spring on the root's roll about the bed's long axis, back to the roll it starts with.
    k[:, 1] = cfg.hold_roll_m * total_mass * GRAVITY_M_S2
    root_start = root_matrix(params.root_rotation)
    ref_local = lying_reference(params.pose, root_roll(params.root_rotation), cfg.lying_extension)
    iters = torch.zeros(B, dtype=torch.long, device=device)
    # Start with the lowest point of each body on the mattress top (a vertical drop).
    pts, corners = layout.points(out.vertices)
    # (B, P, 3): the part transforms and tissue depths round as they always have on this layout.
    pts = pts.transpose(1, 2).contiguous()
    lowest = pts[..., 2].amin(1) if raised is None else raised.drop(pts)
    drop = torch.stack([torch.zeros_like(lowest), torch.zeros_like(lowest), lowest], -1)
    cur = params.replace(root_translation=params.root_translation - drop)
    # The parts ride their joints rigidly while the rest is found: their surface points and
    # centres of mass are kept in each part's joint frame; the mesh is skinned once at the end.
    mass, com = corner_mass_and_com(*(c - drop[:, :, None] for c in corners), layout.triangle_part)
    mass = mass * (total_mass / mass.sum(1))[:, None]  # the parts' shares of the body's mass
    rot, joints = pose_in_mat(rest, cur)
    pts = pts - drop[:, None]
    local_pts = to_part_frames(pts, labels, rot, joints)
    point_tissue = tissue_modulus(
        pts,
        labels,
        joints,
        mp.tissue_pa_per_m,
        cfg.tissue_by_part,
        cfg.tissue_depth,
        cfg.tissue_depth_max,
    )
    point_sag = tissue_sag(pts, labels, joints, cfg.tissue_sag_m, cfg.sag_depth_max)
    local_com = ((com - joints)[..., None, :] @ rot)[..., 0, :]  # R^T (c - p)
    under = under_c = None
    if pillow_m is not None:
        pillow_m = torch.as_tensor(pillow_m, dtype=dtype, device=device).reshape(-1)
        if pillow_m.shape[0] != B or not bool(torch.isfinite(pillow_m).all()) or bool((pillow_m < 0).any()):
            raise UserError(f"pillow_m must hold {B} finite thicknesses >= 0 (m), got {pillow_m.tolist()}")
        if point_tissue is None:
            raise UserError("a pillow needs the soft tissue (MattressParams.tissue_pa_per_m > 0) to rest on")
        if raised is not None:
            raise UserError("pillows lie on flat beds only; drop pillow_m for a raised bed")
        under = footprint(cfg.pillow, joints, xy, pillow_m)
        under_c = None if coarse is None else footprint(cfg.pillow, joints, coarse.xy, pillow_m)
    grids = (xy, None if coarse is None else coarse.xy)
    wedge_m, wedge_c = wedge_thickness(cfg.wedge, root_roll(params.root_rotation), joints, grids, point_tissue, raised)
    contact = None
    if cfg.self_contact:
        contact = SelfContact(fit_capsules(model, params.shape), rot, joints, weight, cfg.self_contact_sink_m)
    friction = Friction(B, mp.friction, dtype, device) if cfg.friction else None
    dof_parts = dofs.desc[dofs.joint]
    nr, nc = fine.nr, fine.nc
    done = RestsDone(params, nr * nc, area, dofs, raised)
    # The bodies still moving and their state; a body whose re-posing no longer moves it leaves
    # (its rest is its last linearisation's solve, finished on its own, so it does not depend
    # on how long the others in its batch take).
    act = torch.arange(B, device=device)
    body = MovingBodies(
        cur, rest, local_com, mass, local_pts, point_tissue, point_sag, dof_lo, dof_hi, ref_local, root_start, k, weight
    )
    body.pillow_m, body.pillow_under, body.wedge_m = pillow_m, under, wedge_m
    vertex = layout.vertex  # the coarse grid's points: the mesh's vertices
    if coarse is not None:
        body.coarse_points(vertex, under_c, wedge_c)
    body.last_q, body.streak = k.new_zeros(B, dofs.n), k.new_zeros(B, dofs.n)
    body.share = torch.ones_like(body.last_q)
    # Each unknown's trust region and settled tolerance (the vertical shift in m, the rest in rad).
    cap = torch.full((dofs.n,), cfg.max_rotation_rad, dtype=dtype, device=device)
    tol = torch.full((dofs.n,), cfg.settled_rotation_rad, dtype=dtype, device=device)
    cap[0], tol[0] = cfg.max_shift_m, cfg.settled_shift_m
    moving_contact, solved = contact, None
    labels_c = labels[vertex]
    in_coarse = coarse is not None
    for outer in range(cfg.outer + 1):
        cur = body.cur
        if outer > 0:
            rot, joints = pose_in_mat(body.rest, cur)
        com = (rot @ body.local_com[..., None])[..., 0] + joints
        body_com = (body.mass[..., None] * com).sum(1) / body.mass.sum(1)[:, None]
        if in_coarse:
            g, pts, lab, sag, tissue, pill = coarse, body.c_pts, labels_c, body.c_sag, body.c_tissue, body.c_under
            wedge = body.c_wedge_m
        else:
            g, pts, lab, sag, tissue = fine, body.local_pts, labels, body.point_sag, body.point_tissue
            pill, wedge = body.pillow_under, body.wedge_m
        h, part, cell_tissue = g.heights(
            pts,
            lab,
            rot,
            joints,
            sag=sag,
            tissue=tissue,
            raised=raised,
            pillow=(body.pillow_m, pill, cfg.pillow),
            wedge=(wedge, cfg.wedge),
        )
        dof_a, e = dof_geometry(dofs, rot, joints, body_com, cur.pose, body.ref_local)
        e[:, 1] = matrix_to_axis_angle(root_matrix(cur.root_rotation) @ body.root_start.transpose(-1, -2))[:, 0]
        axes, pivots = dof_axes_pivots(dofs, rot, joints, body_com)
        section_a = None if raised is None else raised.section_a(dof_a, axes, pivots)
        springs = [] if moving_contact is None else [moving_contact.linearise(rot, joints, axes, pivots, dof_parts)]
        if friction is not None and solved is not None:
            friction.update(rot, joints, *on_sheet(solved, raised))
            springs.append(friction.linearise(rot, joints, axes, pivots, dof_parts))
        lin = Linearised(
            h,
            part,
            g.xy,
            dof_a,
            body.mass,
            com,
            e,
            body.k,
            dofs,
            g.area,
            cell_tissue,
            (dofs.hinge_angles(cur.pose), body.dof_lo, body.dof_hi, _LIMIT_STIFFNESS_RATIO * body.k),
            springs,
            section_a,
            None if raised is None else raised.section_cos,
        )
        last = outer == cfg.outer
        q, it = minimise(
            lin,
            h.new_zeros(len(act), dofs.n),
            mp,
            body.weight,
            cfg,
            max_steps=cfg.inner if last else cfg.coarse_inner if in_coarse else cfg.inner_reposing,
            step_tol=0.0 if last else cfg.reposing_step_tol,
        )
        iters[act] += it
        # The motion the bodies take: all of it, or the swinging unknowns' share (`damp_swings`).
        step = q
        if cfg.damp_swings:
            step, body.share, body.streak = damp_swings(q, body.last_q, body.share, body.streak, cap, tol)
            body.last_q = q
        moved = (step.abs() >= tol).any(1)
        done.reposings[act] = outer
        # No body finishes on the coarse grid, and each takes all its re-posings there (a body's
        # path does not depend on its batch); then the image's grid.
        if not in_coarse and (last or not bool(moved.any())):
            # The last re-posing, or nothing moves any more: each finishes its solve (the last
            # re-posing's already has the rest's step count); it is the rest (not settled if the
            # last re-posing still moved it).
            if not last:
                q, it = minimise(lin, q, mp, body.weight, cfg, max_steps=cfg.inner)
                iters[act] += it
            done.finish(act, lin, q, cur, rot, joints, body_com, mp)
            done.moving[act] = moved & last
            break
        if not in_coarse and not bool(moved.all()):
            # These have settled: their solve goes on to the rest, on their own.
            idx, keep = (~moved).nonzero()[:, 0], moved.nonzero()[:, 0]
            lin_s = lin.take(idx)
            q_s, it = minimise(lin_s, q[idx], mp, body.weight[idx], cfg, max_steps=cfg.inner)
            iters[act[idx]] += it
            done.finish(act[idx], lin_s, q_s, cur.index(idx), rot[idx], joints[idx], body_com[idx], mp)
            if friction is not None:
                solved = tuple(x[keep] for x in lin.contact_state(step, mp))
                friction = friction.take(keep)
            if moving_contact is not None:
                moving_contact = moving_contact.take(keep)
            act, body, q, step = act[keep], body.take(keep), q[keep], step[keep]
            rot, joints, body_com = rot[keep], joints[keep], body_com[keep]
        elif friction is not None:  # the contacts where the bodies go (their damped motion)
            solved = lin.contact_state(step, mp)
        if in_coarse and outer + 1 >= n_coarse:
            in_coarse = False  # (and each unknown's swing damping starts again on the image's grid)
            body.last_q.zero_(), body.share.fill_(1.0), body.streak.zero_()
            body.coarse_points(None, None)
        body.cur = apply_motion(body.cur, step, dofs, rot, joints, body_com)
    final = done.params
    out = model(final)
    penetration = (
        torch.zeros(B, dtype=dtype, device=device)
        if contact is None
        else contact.penetration(*pose_in_mat(rest, final))
    )
    foundation = done.foundation.view(B, nr, nc)
    if under is not None:  # what the mat reads beneath the pillows (the cell centres from above)
        foundation = spread_load(foundation, under.view(B, nr, nc), cfg.pillow, pillow_m, X[:, 0], Y[0])
    if wedge_m is not None:  # and beneath the wedges
        foundation = rigid_base(foundation, wedge_m.view(B, nr, nc) > 0, X[:, 0], Y[0])
    force, w_max = done.force, done.max_compression
    failure = done.failures(params.root_rotation, weight, mp)
    bad = torch.tensor([bool(x) for x in failure], device=device)
    foundation = torch.where(bad[:, None, None], torch.zeros_like(foundation), foundation)
    return ArticulatedRest(
        params=final,
        vertices=out.vertices,
        joints=out.joints,
        foundation_pa=foundation,
        force_n=force,
        max_compression_m=w_max,
        part_force_n=done.part_force,
        self_penetration_m=penetration,
        iterations=iters,
        reposings=done.reposings,
        settled=~done.moving,
        failure=failure,
        sub=cfg.sub,
        pillow_m=pillow_m,
        friction_ratio=None if raised is None else done.friction_ratio,
    )


__all__ = [
    "ENGINE_REVISION",
    "FAIL_BOTTOM",
    "FAIL_SLIDES",
    "FAIL_TILT",
    "ArticulatedConfig",
    "ArticulatedRest",
    "rest_articulated",
]
