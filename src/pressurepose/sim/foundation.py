"""Sim #2: the rigid posed mesh at static rest on a nonlinear elastic-foundation mattress.

Model (docs/physics.md): the mattress top is a grid over the covered area (68 x 33 taxels,
each split `sub` x `sub`). Where the body's underside reaches below the undeformed top by w,
the foam pushes back with p(w) = k1 w + k3 w^3 (MattressParams). The body is rigid; its rest
is the vertical shift dz and the small roll a (about the bed's long axis) and pitch b (about
the cross axis) through its centre of mass at which the foam's force equals the weight and
its moments about the centre of mass vanish:

    sum_i p(w_i) A = m g,   sum_i p(w_i) A (y_i - y_c) = 0,   sum_i p(w_i) A (x_i - x_c) = 0,
    w_i = max(0, -(h_i + dz + a (y_i - y_c) - b (x_i - x_c)))

with h_i the underside height over cell i (`maps.underside_height`). Newton's method solves it
(a safeguarded depth search, then Newton with the analytic 3 x 3 Jacobian and backtracking).
The motion is applied to the mesh as an exact rigid motion; when the tilt exceeds 0.02 rad
the mesh is rasterised again and the (small) remainder solved about the new pose. The
pressure returned is the last solve's field, so force and moments balance exactly; the mesh
moved rigidly differs from it only by the sideways shift of its points (tilt x height, ~1 mm).
The mat and cover couple taxels laterally: the recorded pressure is the foundation pressure spread by a normalised Gaussian of width `spread_m`,
which keeps the total force and the centre of pressure. The covered area is simulated; the
sensing 64 x 27 taxels are recorded.

Gradients: the converged rest is made differentiable by the implicit function theorem (one
Newton step evaluated with autograd at the solution, Jacobian held fixed), so the pressure is
differentiable with respect to the vertices, the mass and every MattressParams field given
as a tensor. Batched over B bodies; CPU or CUDA; float32 or float64.
"""

from __future__ import annotations

import dataclasses

import torch

from pressurepose.bed import BedShape
from pressurepose.maps import EMPTY_HEIGHT_M, cell_centres, centroid_and_points, heights_from_points
from pressurepose.mat import MatSpec
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams
from pressurepose.sim.reading import taxel_pressure

# Why a solve can fail (per sample). Empty string: converged.
FAIL_NO_SUPPORT = "no support: the body does not reach the mattress or is off it"
FAIL_TILT = "unstable: the centre of mass lies outside the support (tilt beyond limit)"
FAIL_BOTTOM = "sank through the mattress (compression beyond its thickness)"
FAIL_NOT_CONVERGED = "did not converge"
FAIL_SLIDES = "slides: the raised bed needs more friction than the sheet has"

MAX_TILT_RAD = 0.35
SMALL_TILT_RAD = 0.02  # below it one pass is enough (the linearised rest is rigid to 2e-4)


@dataclasses.dataclass
class PressureResult:
    """Sim #2's rest of B bodies. Pressures in Pa on the covered grid, before the sensor."""

    pressure_pa: torch.Tensor  # (B, covered_rows, covered_cols) per taxel, after spreading
    foundation_pa: torch.Tensor  # (B, covered_rows*sub, covered_cols*sub) before spreading
    vertices: torch.Tensor  # (B, V, 3) the mesh at rest (mat frame, m)
    shift_m: torch.Tensor  # (B,) total vertical shift applied
    tilt_rad: torch.Tensor  # (B, 2) roll about x, pitch about y (through the COM)
    force_n: torch.Tensor  # (B,) total foundation force
    max_compression_m: torch.Tensor  # (B,)
    iterations: torch.Tensor  # (B,) Newton iterations (both passes)
    failure: list[str]  # (B,) "" when at rest, else the reason
    sub: int
    friction_ratio: torch.Tensor | None = None  # (B,) tangential / normal force the bed needs (0 when flat)
    rotation: torch.Tensor | None = None  # (B, 3, 3) and translation (B, 3): vertices_out = R v_in + t
    translation: torch.Tensor | None = None

    @property
    def ok(self) -> torch.Tensor:
        return torch.tensor([not f for f in self.failure], device=self.shift_m.device)


class _Grid:
    """The cells under a body (packed: only cells with body above them), with per cell its
    normal nu, its tangent tau along the bed, its world point r relative to the centre of mass,
    and how a small rigid motion (dz, roll a, pitch b) changes the body's height along the
    normal: c = (nu_z, nu_z r_y, nu_x r_z - nu_z r_x) (flat bed: (1, dy, -dx)).

    Unknowns q = (dz, a, b, mu): mu is the friction the bed mobilises, a tangential force
    mu x the normal force at every loaded cell (0 on a flat bed, where nothing pulls the body
    along the bed). Residual: vertical force - weight, moments about x and y through the
    centre of mass, force along the bed."""

    def __init__(self, h, mat, sub, com, bed: BedShape | None = None, params: MattressParams | None = None):
        B = h.shape[0]
        self.shape = h.shape
        S, Y = cell_centres(mat, sub, covered=True, dtype=h.dtype, device=h.device)
        flat = h.reshape(B, -1)
        valid = flat < EMPTY_HEIGHT_M
        K = max(int(valid.sum(1).max()), 1)
        self.index = torch.argsort((~valid).to(torch.int8), dim=1, stable=True)[:, :K]
        self.h = flat.gather(1, self.index)
        self.mask = valid.gather(1, self.index).to(h.dtype)
        self.area = mat.pitch_row_m * mat.pitch_col_m / sub**2
        s_cells, y_cells = S.reshape(-1)[self.index], Y.reshape(-1)[self.index]
        if params is not None and params.has_cells:  # heights above the air cells' top
            self.h = self.h - params.top_height(s_cells) * self.mask
        bed = bed or BedShape()
        self.nu, self.tau, base = bed.frame_at(s_cells, mat)
        self.r = base + torch.stack([torch.zeros_like(y_cells), y_cells, torch.zeros_like(y_cells)], -1) - com[:, None]
        nx, nz = self.nu[..., 0], self.nu[..., 2]
        self.c = torch.stack([nz, nz * self.r[..., 1], nx * self.r[..., 2] - nz * self.r[..., 0]], -1)
        # A cell force F (in the xz plane) enters the balance as (F_z, r_y F_z, r_x F_z - r_z F_x,
        # F_x). With F = f (nu + mu tau): balance = f (N + mu T), N and T per cell, stored
        # transposed (B, 4, K) so residual and Jacobian are batched matrix products.
        r = self.r

        def rows(vx, vz):
            return torch.stack([vz, r[..., 1] * vz, r[..., 0] * vz - r[..., 2] * vx, vx], 1)

        self.NT = rows(self.nu[..., 0], self.nu[..., 2]).contiguous()
        self.TT = rows(self.tau[..., 0], self.tau[..., 2]).contiguous()

    def compression(self, q):
        hq = self.h + torch.bmm(self.c, q[:, :3, None])[..., 0]
        return torch.relu(-hq) * self.mask

    def residual(self, q, params, weight):
        """(B, 4) residual (N, N m, N m, N) and the cell forces and compressions (packed)."""
        w = self.compression(q)
        f = params.foundation_pressure(w) * self.area
        R = torch.bmm(self.NT + q[:, 3, None, None] * self.TT, f[..., None])[..., 0]
        R = R - torch.stack([weight, torch.zeros_like(weight), torch.zeros_like(weight), torch.zeros_like(weight)], -1)
        return R, f, w

    def jacobian(self, q, params):
        w = self.compression(q)
        k = params.foundation_stiffness(w) * self.area * (w > 0).to(w.dtype)
        f = params.foundation_pressure(w) * self.area
        A = self.NT + q[:, 3, None, None] * self.TT
        J_motion = -torch.bmm(A, k[..., None] * self.c)  # through f
        J_mu = torch.bmm(self.TT, f[..., None])  # mu directly
        return torch.cat([J_motion, J_mu], -1)

    def depth_slope(self, q, params):
        """d(vertical force)/d(dz) (B,): phase 1 of the solve needs only this."""
        w = self.compression(q)
        k = params.foundation_stiffness(w) * self.area * (w > 0).to(w.dtype)
        ez = self.nu[..., 2] + q[:, 3, None] * self.tau[..., 2]
        return -(k * self.c[..., 0] * ez).sum(1)

    def unpack(self, values):
        """Packed (B, K) -> the full (B, rows, cols) grid (zeros elsewhere)."""
        out = values.new_zeros(self.shape[0], self.shape[1] * self.shape[2])
        return out.scatter(1, self.index, values * self.mask).view(self.shape)


def _merit(R, weight):
    """Scalar residual size per sample: forces in weights, moments in weight x 10 cm."""
    return (R[:, 0].abs() + R[:, 3].abs() + (R[:, 1].abs() + R[:, 2].abs()) / 0.1) / weight


def _newton(grid: _Grid, params, weight, q0, max_iter, tol):
    """Solve grid.residual(q) = 0 from q0 without gradients. Returns q, iterations, converged.

    Phase 1 finds the depth that carries the weight with the tilt held (a safeguarded 1-D
    Newton on the monotone force; bisection once bracketed), phase 2 runs Newton on all three
    unknowns with backtracking on the residual, so thin contact patches (nearly singular
    tilt rows) cannot throw the body around."""
    B = q0.shape[0]
    q = q0.clone()
    iters = torch.zeros(B, dtype=torch.long, device=q.device)
    # Nothing of the body over the mattress: no support to find (reported by the caller).
    dead = ~grid.mask.bool().flatten(1).any(1)
    thick = float(_detached(params).thickness_m)
    # Phase 1: depth. The force falls as dz grows (shallower): F < W at dz puts the root
    # below dz (upper bound ub), F > W above it (lower bound lb).
    ub = torch.full_like(q[:, 0], float("inf"))
    lb = torch.full_like(q[:, 0], -float("inf"))
    done = dead.clone()
    for _ in range(max_iter):
        R, _, _ = grid.residual(q, params, weight)
        done = done | (R[:, 0].abs() < 1e-3 * weight)
        if bool(done.all()):
            break
        slope = grid.depth_slope(q, params)
        short = R[:, 0] < 0
        ub = torch.where(short, torch.minimum(ub, q[:, 0]), ub)
        lb = torch.where(~short, torch.maximum(lb, q[:, 0]), lb)
        d_newton = torch.where(
            slope < 0, -R[:, 0] / torch.where(slope < 0, slope, -torch.ones_like(slope)), torch.full_like(slope, -0.02)
        ).clamp(-0.02, 0.02)
        cand = q[:, 0] + d_newton
        bracketed = torch.isfinite(ub) & torch.isfinite(lb)
        cand = torch.where(bracketed & ((cand >= ub) | (cand <= lb)), (ub + lb) / 2, cand)
        q[:, 0] = torch.where(done, q[:, 0], cand)
        iters = iters + (~done).long()
        done = done | (q[:, 0] < q0[:, 0] - 2 * thick)
    # Phase 2: depth, roll, pitch and the friction ratio.
    step_max = torch.tensor([0.02, 0.05, 0.05, 0.5], dtype=q.dtype, device=q.device)
    eye = torch.eye(4, dtype=q.dtype, device=q.device)
    R, _, _ = grid.residual(q, params, weight)
    merit = _merit(R, weight)
    done = dead | ((R.abs() / weight[:, None]).amax(-1) < tol)
    for _ in range(max_iter):
        if bool(done.all()):
            break
        J = grid.jacobian(q, params)
        diag = J.diagonal(dim1=-2, dim2=-1).abs()
        reg = (1e-9 * weight[:, None] + 1e-6 * diag.amax(-1, keepdim=True))[..., None] * eye
        step = torch.linalg.solve(J - reg, -R[..., None])[..., 0]
        step = torch.maximum(torch.minimum(step, step_max), -step_max)
        step = torch.where(done[:, None], torch.zeros_like(step), step)
        # Backtracking: halve the step until the residual shrinks (at most 6 times).
        t = torch.ones(B, dtype=q.dtype, device=q.device)
        for _ in range(6):
            R_new, _, _ = grid.residual(q + t[:, None] * step, params, weight)
            better = _merit(R_new, weight) < merit
            if bool((better | done).all()):
                break
            t = torch.where(better | done, t, t / 2)
        q = q + t[:, None] * step
        R, _, _ = grid.residual(q, params, weight)
        merit = _merit(R, weight)
        iters = iters + (~done).long()
        done = done | ((R.abs() / weight[:, None]).amax(-1) < tol)
        # Hopeless samples stop early (the caller reports them): tipped over.
        done = done | (q[:, 1:3].abs() > MAX_TILT_RAD).any(1)
    return q, iters, done


def _motion(com, q):
    """The rigid motion of `_rotate` as (R (B, 3, 3), t (B, 3)): v -> R v + t."""
    a, b = q[:, 1], q[:, 2]
    ca, sa, cb, sb = torch.cos(a), torch.sin(a), torch.cos(b), torch.sin(b)
    one, zero = torch.ones_like(a), torch.zeros_like(a)
    Rx = torch.stack([one, zero, zero, zero, ca, -sa, zero, sa, ca], -1).view(-1, 3, 3)
    Ry = torch.stack([cb, zero, sb, zero, one, zero, -sb, zero, cb], -1).view(-1, 3, 3)
    R = Ry @ Rx
    t = com - (R @ com[..., None])[..., 0] + torch.stack([zero, zero, q[:, 0]], -1)
    return R, t


def simulate_pressure(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    mass_kg: torch.Tensor,
    params: MattressParams | None = None,
    mat: MatSpec | None = None,
    sub: int = 2,
    max_iter: int = 60,
    tol: float = 1e-6,
    passes: int = 2,
    bed: BedShape | None = None,
) -> PressureResult:
    """Rest the rigid meshes (B, V, 3) (mat frame, m; faces (F, 3)) of mass (B,) kg on the
    mattress and return the pressure on the covered grid (Pa) and the mesh at rest.

    The meshes may start anywhere above or in the mattress; their horizontal placement and
    yaw are kept. Failures (no support, tilting off, bottoming out, no convergence) are
    reported per sample in `failure`, never as NaN: their pressure is set to zero.
    """
    params = params or MattressParams()
    mat = mat or MatSpec()
    if vertices.ndim != 3 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices must have shape (B, V, 3), got {tuple(vertices.shape)}")
    if not torch.isfinite(vertices).all():
        raise ValueError("vertices contain NaN or infinite values; pose the body with finite parameters")
    mass_kg = torch.as_tensor(mass_kg, dtype=vertices.dtype, device=vertices.device).reshape(-1)
    if mass_kg.shape[0] != vertices.shape[0]:
        raise ValueError(f"mass_kg must have one value per body ({vertices.shape[0]}), got {mass_kg.shape[0]}")
    if not torch.isfinite(mass_kg).all() or bool((mass_kg <= 0).any()):
        raise ValueError("mass_kg must be finite and > 0 for every body")
    faces = faces.to(vertices.device)
    weight = mass_kg * GRAVITY_M_S2
    B = vertices.shape[0]
    total_q = vertices.new_zeros(B, 3)
    mu = vertices.new_zeros(B)
    R_acc = torch.eye(3, dtype=vertices.dtype, device=vertices.device).expand(B, 3, 3)
    t_acc = vertices.new_zeros(B, 3)
    iters = torch.zeros(B, dtype=torch.long, device=vertices.device)
    verts = vertices
    # Centroid and surface points once; later passes move them with the mesh (rigid motion).
    com, world_points = centroid_and_points(verts, faces)
    for p in range(passes):
        points = bed.to_surface(world_points, mat) if bed is not None and not bed.flat else world_points
        h = heights_from_points(points, mat, sub=sub, covered=True)
        grid = _Grid(h, mat, sub, com, bed, params)
        with torch.no_grad():
            hd = h.detach()
            gd = _Grid(hd, mat, sub, com.detach(), bed, _detached(params))
            q0 = verts.new_zeros(B, 4)
            q0[:, 3] = mu.detach()
            if p == 0:
                # Start with the lowest supported point on the surface.
                lowest = torch.where(gd.mask.bool(), gd.h, torch.full_like(gd.h, float("inf"))).amin(1)
                q0[:, 0] = torch.where(torch.isfinite(lowest), -lowest, torch.zeros_like(lowest))
            pd = _detached(params)
            qs, it, _ = _newton(gd, pd, weight.detach(), q0, max_iter, tol)
            iters += it
            J = gd.jacobian(qs, pd)
            eye = torch.eye(4, dtype=J.dtype, device=J.device)
            Jinv = torch.linalg.inv(J - 1e-9 * weight.detach()[:, None, None] * eye)
        # Implicit-function step: value qs, gradient -J^-1 dR/dtheta.
        R, _, _ = grid.residual(qs, params, weight)
        q = qs - (Jinv @ R[..., None])[..., 0]
        q = q + (qs - q).detach()  # keep the converged value exactly
        total_q = total_q + q[:, :3]
        mu = q[:, 3]
        R_p, t_p = _motion(com, q)
        verts = verts @ R_p.transpose(1, 2) + t_p[:, None]
        world_points = world_points @ R_p.transpose(1, 2) + t_p[:, None]
        com_next = (R_p @ com[..., None])[..., 0] + t_p
        R_acc, t_acc = R_p @ R_acc, (R_p @ t_acc[..., None])[..., 0] + t_p
        if p == passes - 1 or float(qs[:, 1:3].abs().max()) <= SMALL_TILT_RAD:
            # The pressure is this pass's solved field (exact balance); the mesh is moved by
            # the same motion rigidly, which shifts its points sideways by at most
            # tilt x height (~1 mm), so there is no need to rasterise it again.
            break
        com = com_next
    R, f_packed, w_packed = grid.residual(q, params, weight)
    f, w = grid.unpack(f_packed), grid.unpack(w_packed)
    foundation = f / grid.area
    failure = []
    tilt = total_q[:, 1:].detach()
    has_cells = grid.mask.bool().any(1)
    f_d, w_d, R_d = f.detach(), w.detach(), R.detach()
    thick_m = float(_detached(params).thickness_m)
    for i in range(B):
        if not bool(has_cells[i]) or float(f_d[i].sum()) <= 0:
            failure.append(FAIL_NO_SUPPORT)
        elif float(tilt[i].abs().max()) > MAX_TILT_RAD:
            failure.append(FAIL_TILT)
        elif float(w_d[i].max()) > thick_m:
            failure.append(FAIL_BOTTOM)
        elif abs(float(mu[i].detach())) > float(_detached(params).friction):
            failure.append(FAIL_SLIDES)
        elif float((R_d[i].abs() / weight[i].detach()).max()) > 1e-3:
            failure.append(FAIL_NOT_CONVERGED)
        else:
            failure.append("")
    bad = torch.tensor([bool(x) for x in failure], device=verts.device)
    foundation = torch.where(bad[:, None, None], torch.zeros_like(foundation), foundation)
    pressure = taxel_pressure(foundation, params, mat, sub)
    return PressureResult(
        pressure_pa=pressure,
        foundation_pa=foundation,
        vertices=verts,
        shift_m=total_q[:, 0],
        tilt_rad=total_q[:, 1:],
        force_n=f.sum((1, 2)),
        max_compression_m=w.amax((1, 2)),
        iterations=iters,
        failure=failure,
        sub=sub,
        friction_ratio=mu,
        rotation=R_acc,
        translation=t_acc,
    )


def _detached(params: MattressParams) -> MattressParams:
    changes = {}
    for f in dataclasses.fields(params):
        v = getattr(params, f.name)
        if isinstance(v, torch.Tensor):
            changes[f.name] = v.detach()
    return dataclasses.replace(params, **changes) if changes else params


__all__ = [
    "FAIL_BOTTOM",
    "FAIL_NOT_CONVERGED",
    "FAIL_NO_SUPPORT",
    "FAIL_SLIDES",
    "FAIL_TILT",
    "PressureResult",
    "simulate_pressure",
]
