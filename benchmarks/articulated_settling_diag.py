"""Why the articulated rest's re-posings do not settle: per re-posing, which unknowns move and
the energy before / after it, the linearised prediction against the true re-posed configuration.

    OMP_NUM_THREADS=1 python benchmarks/articulated_settling_diag.py [--partition general] [--n 8]
        [--first 0] [--outer 14] [--bodies 0,3] [--quiet] [--set friction=False,inner_reposing=12]

Each body is rested alone (B = 1; the engine's rest of a body does not depend on its batch),
the engine's `minimise` and `Linearised` wrapped to record every solve. Per solve i at posing
P_i: E = the true energy at P_i (gravity on the parts' absolute heights + joint springs + hinge
limits + foam and tissue + self-contact + friction with P_i's anchors: the linearised energy at
q = 0), pred = the linearised change at the solve's q_i; then, without friction (its anchors
move between re-posings), the predicted and the true change to the next solve's posing P_{i+1}
and the true-minus-predicted per term; where the true energy rose by more than 0.5 J, the
foam's true-minus-predicted per J24 part (a part with ~0 predicted foam energy that has much at
P_{i+1} was hidden: not the lowest point of its cells when linearised). "posings" counts every
linearisation (rejected re-posing steps included, engines from settle5 on).
"""

from __future__ import annotations

import argparse
from collections import Counter

import torch

import pressurepose.sim.articulated as art
from pressurepose.body import load_body_model
from pressurepose.body.joints import J24_NAMES
from pressurepose.sampling.partitions import SamplingConfig
from pressurepose.sampling.sampler import PoseSampler
from pressurepose.sim.articulation import Dofs
from pressurepose.sim.friction import CoulombSprings
from pressurepose.sim.mattress import GRAVITY_M_S2, MattressParams
from pressurepose.sim.run import articulated_config_for


class _Lin(art.Linearised):
    """The engine's linearisation, keeping the parts' absolute potential energy."""

    def __init__(self, h, part, xy, dof_a, mass, com, e, k, dofs, area, tissue=None, limits=None, springs=()):
        super().__init__(h, part, xy, dof_a, mass, com, e, k, dofs, area, tissue, limits, springs)
        self.grav_abs = (mass * GRAVITY_M_S2 * com[..., 2]).sum(1)
        _Lin.built += 1

    built = 0

    def take(self, idx):
        new = super().take(idx)
        new.__class__ = _Lin
        new.grav_abs = self.grav_abs[idx]
        return new

    def parts(self, q, mp):
        """Energy terms at q (floats, body 0)."""
        w = self.compression(q)
        out = {
            "grav": float(self.grav_abs[0] + (self.g_grav * q).sum(1)[0]),
            "spring": float((0.5 * (self.k * (self.e + q) ** 2).sum(1))[0]),
            "limit": float(self._limit(q)[0][0]),
            "foam": float((self._law(mp).energy(w).sum(1) * self.area)[0]),
            "self": 0.0,
            "fric": 0.0,
        }
        for s in self.springs:
            out["fric" if isinstance(s, CoulombSprings) else "self"] += float(s.energy(q)[0])
        out["total"] = sum(out.values())
        e_cell = self._law(mp).energy(w) * self.area
        self.foam_part = torch.zeros(24, dtype=w.dtype).scatter_add_(0, self.part[0], e_cell[0])
        return out


def dof_names(dofs: Dofs) -> list[str]:
    names = []
    for n, (j, hinge, world) in enumerate(zip(dofs.joint.tolist(), dofs.axis_body, dofs.axis_world, strict=True)):
        if n == 0:
            names.append("dz")
        elif j == 0:
            names.append("root_" + ("roll" if n == 1 else "pitch"))
        else:
            names.append(J24_NAMES[j] + ("_hinge" if hinge is not None else "_x" if world[0] else "_y"))
    return names


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--partition", default="general")
    ap.add_argument("--n", type=int, default=8)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--outer", type=int, default=14)
    ap.add_argument("--bodies", default=None, help="comma-separated body indices (default: first..first+n)")
    ap.add_argument("--quiet", action="store_true", help="one line per body")
    ap.add_argument("--set", default="", help="ArticulatedConfig overrides, e.g. friction=False,inner_reposing=12")
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_body_model("anny", dtype=torch.float64)
    bed = MattressParams.preset("sponge")
    idx = [int(x) for x in args.bodies.split(",")] if args.bodies else list(range(args.first, args.first + args.n))
    poses = (
        PoseSampler(model, SamplingConfig(partition=args.partition, gender="female", seed=0))
        .sample(range(max(idx) + 1))
        .params
    )
    import dataclasses

    over = {k: eval(v) for k, v in (kv.split("=") for kv in args.set.split(",") if kv)}  # noqa: S307
    config = dataclasses.replace(articulated_config_for(args.partition), outer=args.outer, **over)
    names = dof_names(Dofs("cpu", torch.float64))
    calls: list = []
    real_minimise = art.minimise

    def spy(lin, q0, mp, weight, cfg, max_steps, step_tol=0.0):
        q, it = real_minimise(lin, q0, mp, weight, cfg, max_steps, step_tol)
        calls.append((lin, q0.clone(), q.clone(), int(it[0])))
        return q, it

    art.minimise, art.Linearised = spy, _Lin
    summary = Counter()
    try:
        for b in idx:
            calls.clear()
            _Lin.built = 0
            rest = art.rest_articulated(model, poses.index(torch.tensor([b])), mattress=bed, config=config)
            # Re-posings: one call per distinct linearisation (a repeated lin is its rest's solve).
            rep = []
            for lin, q0, q, it in calls:
                if rep and rep[-1][0] is lin:
                    rep[-1] = (lin, rep[-1][1], q, rep[-1][3] + it)
                else:
                    rep.append((lin, q0, q, it))
            rises, lin_err = 0, []
            lines = []
            for i, (lin, _, q, it) in enumerate(rep):
                e0 = lin.parts(torch.zeros_like(q), bed)
                pred = lin.parts(q, bed)
                nxt = rep[i + 1][0].parts(torch.zeros_like(q), bed) if i + 1 < len(rep) else None
                big = (q[0].abs() > torch.tensor([3e-4] + [5e-3] * (q.shape[1] - 1))).nonzero()[:, 0].tolist()
                moves = ", ".join(f"{names[n]} {float(q[0, n]):+.3f}" for n in big[:6]) + (
                    " ..." if len(big) > 6 else ""
                )
                line = f"  r{i:2d} it {it:2d} E {e0['total']:+.4f} pred {pred['total'] - e0['total']:+.4f}"
                if nxt is not None:
                    # true change without friction (its anchors move between re-posings)
                    tr = (nxt["total"] - nxt["fric"]) - (e0["total"] - e0["fric"])
                    pr = (pred["total"] - pred["fric"]) - (e0["total"] - e0["fric"])
                    terms = " ".join(
                        f"{k} {nxt[k] - pred[k]:+.4f}" for k in ("grav", "spring", "limit", "foam", "self")
                    )
                    line += f" | exfric pred {pr:+.4f} true {tr:+.4f} (true-pred: {terms})"
                    rises += tr > 0
                    if tr > 0.5:
                        fp_pred = lin.foam_part.clone() if lin.parts(q, bed) else None
                        rep[i + 1][0].parts(torch.zeros_like(q), bed)
                        d = rep[i + 1][0].foam_part - fp_pred
                        top = d.abs().argsort(descending=True)[:4].tolist()
                        line += (
                            " [foam per part true-pred: "
                            + ", ".join(f"{J24_NAMES[j]} {float(d[j]):+.2f} ({float(fp_pred[j]):.2f})" for j in top)
                            + "]"
                        )
                    lin_err.append(tr - pr)
                lines.append(line + f" | {len(big)} move: {moves}")
            settled = _Lin.built < config.outer + 1
            summary["settled"] += settled
            summary["bodies"] += 1
            print(
                f"body {b}: solves {len(rep)} posings {_Lin.built}, settled {settled}, Newton {int(rest.iterations[0])}, "
                f"true energy rose (ex friction) in {rises} of {len(rep) - 1}, failure {rest.failure[0]!r}",
                flush=True,
            )
            if not args.quiet:
                print("\n".join(lines), flush=True)
    finally:
        art.minimise, art.Linearised = real_minimise, art.Linearised
    print(f"settled {summary['settled']} of {summary['bodies']}")


if __name__ == "__main__":
    main()
