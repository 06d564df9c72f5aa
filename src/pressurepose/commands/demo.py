"""`pressurepose demo`: the whole system on embedded defaults, in a few minutes on a laptop CPU.

1. generates a few fresh samples with the physics (sampling, sim #1, sim #2, sensor; the `tiny`
   preset: one sample per row of seed Table 4 and split) into OUT/data, with a contact sheet;
2. estimates their bodies from the pressure images with the packaged default network and
   scores them against the simulated truth (`evaluate`: 3DVPE, MPJPE, cases) into OUT/synthetic;
3. runs the same network on the packaged real PmatData recordings (`evaluate-real`: posture from
   the estimated root roll, height and mass against the subjects') into OUT/real;
4. writes OUT/report.md and OUT/demo.json with the headline numbers and where everything is.

Every step is the library call behind the matching subcommand, so the demo shows what a user's
own run of those commands gives. A second run in the same folder reuses the generated samples
(generation resumes, and a finished dataset is complete).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np

from pressurepose.commands.evaluate import EvaluateConfig, run_evaluate
from pressurepose.commands.evaluate_real import RealEvalConfig, run_evaluate_real
from pressurepose.commands.info import dataset_info
from pressurepose.files import write_text
from pressurepose.generate.plan import GenerateConfig
from pressurepose.generate.run import run_generate
from pressurepose.models import resolve_model
from pressurepose.train.checkpoint import read_model

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class DemoConfig:
    out: Path = Path("out/demo")
    """Output folder (created): data/, synthetic/, real/, report.md, demo.json."""
    model: Path = Path("default")
    """Network: a `pressurepose train` run folder; "default" = the packaged model."""
    pmatdata: Path = Path("pmatdata")
    """PmatData folder (index.csv, experiment-ii/); "pmatdata" = the packaged copy."""
    seed: int = 0
    """Seed of the generated samples (another seed, other bodies)."""
    workers: int = 2
    """Processes simulating the samples."""
    progress: bool = True
    """Show the generation's progress bar."""


def run_demo(cfg: DemoConfig) -> dict[str, Path]:
    """Run the four steps; returns the paths of report.md, demo.json and each step's report."""
    out = Path(cfg.out)
    model_dir = resolve_model(cfg.model)
    _, record = read_model(model_dir)  # fails early, before any simulation, on a bad --model
    backend = record.get("net", {}).get("backend", "anny")
    timings = {}

    t0 = time.perf_counter()
    data = out / "data"
    log.info("1/3 generating fresh samples into %s", data)
    run_generate(
        GenerateConfig(out=data, preset="tiny", seed=cfg.seed, workers=cfg.workers, backend=backend),
        progress=cfg.progress,
    )
    info = dataset_info(data, sheet=12, seed=cfg.seed)
    timings["generate_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    log.info("2/3 estimating the generated bodies with %s", model_dir)
    synthetic = run_evaluate(
        EvaluateConfig(data=data, model=model_dir, out=out / "synthetic", split="test", failures=4)
    )
    timings["synthetic_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    log.info("3/3 estimating bodies on real PmatData recordings")
    real = run_evaluate_real(RealEvalConfig(model=model_dir, pmatdata=cfg.pmatdata, out=out / "real"))
    timings["real_s"] = time.perf_counter() - t0

    summary = _summary(synthetic.record, real.record)
    summary.update(
        model=str(model_dir), seed=cfg.seed, samples=info["total"], seconds={k: round(v, 1) for k, v in timings.items()}
    )
    paths = {"synthetic": synthetic["markdown"], "real": real["markdown"]}
    paths["json"] = write_text(out / "demo.json", json.dumps(summary, indent=1))
    paths["markdown"] = write_text(out / "report.md", _markdown(summary))
    return paths


def _summary(synthetic: dict, real: dict) -> dict:
    """The headline numbers of both reports (metres, kg, shares)."""
    rows = real["per_frame"]
    height_err = np.array([abs(r["estimated_height_m"] - r["height_m"]) for r in rows])
    o = synthetic["overall"]
    return {
        "synthetic": {
            "count": synthetic["count"],
            "vpe_m": o["vpe_m"]["mean"],
            "mpjpe_m": o["mpjpe_m"]["mean"],
            "baselines": {k: v["mean"] for k, v in synthetic["baselines_vpe_m"].items()},
        },
        "real": {
            "frames": len(rows),
            "posture_accuracy": float(np.mean([r["posture"] == r["estimated_posture"] for r in rows])),
            "height_median_abs_error_m": float(np.median(height_err)),
            "mass_median_abs_error_kg": float(np.median([abs(r["estimated_mass_kg"] - r["mass_kg"]) for r in rows])),
            "by_mattress": {
                m: {"posture_accuracy": s["posture_accuracy"], "height_mae_m": s["height_mae_m"]}
                for m, s in real["by_mattress"].items()
            },
            # group E's tilted bodies (20 / 40 deg on wedges or a pillow): read turned toward their side
            "tilted_turned": {m: s["share_turned"] for m, s in real.get("tilted", {}).get("by_mattress", {}).items()},
            # group F's raised beds (head of the bed 0-60 deg): read supine, and the heights
            "raised": {
                m: {"supine": s["posture_accuracy"], "height_median_signed_m": s["height_median_signed_m"]}
                for m, s in real.get("raised", {}).get("by_mattress", {}).items()
            },
        },
    }


def _markdown(s: dict) -> str:
    syn, real = s["synthetic"], s["real"]
    lines = [
        "# pressurepose demo",
        "",
        f"Network: `{s['model']}`. Seconds: " + ", ".join(f"{k[:-2]} {v}" for k, v in s["seconds"].items()) + ".",
        "",
        f"## Synthetic: {s['samples']} fresh samples simulated (seed {s['seed']}), {syn['count']} test samples estimated",
        "",
        f"- 3DVPE {syn['vpe_m'] * 100:.2f} cm, MPJPE {syn['mpjpe_m'] * 1000:.0f} mm "
        "(the seed's best synthetic 3DVPE: ~3.9-4.0 cm)",
    ]
    lines += [f"- baseline {k}: 3DVPE {v * 100:.2f} cm" for k, v in syn["baselines"].items()]
    lines += [
        "- tables per partition, cases and failures: [synthetic/report.md](synthetic/report.md), "
        "samples: [data/contact_sheet.png](data/contact_sheet.png)",
        "",
        f"## Real: PmatData experiment II, {real['frames']} frames",
        "",
        f"- posture (supine/left/right from the estimated root roll): {real['posture_accuracy'] * 100:.1f}% correct",
        f"- height: median absolute error {real['height_median_abs_error_m'] * 100:.1f} cm; "
        f"mass: {real['mass_median_abs_error_kg']:.1f} kg",
    ]
    lines += [
        f"- {m}: posture {v['posture_accuracy'] * 100:.1f}%, height MAE {v['height_mae_m'] * 100:.1f} cm"
        for m, v in real["by_mattress"].items()
    ]
    if real["tilted_turned"]:
        lines.append(
            "- tilted on wedges or a pillow (group E), read turned 10-135 deg toward their side: "
            + ", ".join(f"{m} {v * 100:.0f}%" for m, v in real["tilted_turned"].items())
        )
    if real.get("raised"):
        lines.append(
            "- head of the bed raised 0-60 deg (group F, outside the flat-bed scope), read supine: "
            + ", ".join(
                f"{m} {v['supine'] * 100:.0f}% (height error {v['height_median_signed_m'] * 100:+.1f} cm)"
                for m, v in real["raised"].items()
            )
        )
    lines += [
        "- per frame, confusion and scatter: [real/real.md](real/real.md)",
        "",
        "Browse it: `pressurepose view` on the synthetic report or the data folder.",
        "",
    ]
    return "\n".join(lines)


def demo(cfg: DemoConfig) -> None:
    """The whole system on embedded defaults: simulate fresh samples, estimate their bodies with
    the packaged network, run it on real PmatData recordings; report.md in --out."""
    paths = run_demo(cfg)
    print(Path(paths["markdown"]).read_text())
    print(f"demo report: {paths['markdown']}")


__all__ = ["DemoConfig", "demo", "run_demo"]
