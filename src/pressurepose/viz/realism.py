"""Figure of the realism report: mean real vs mean simulated image, aligned, and profiles."""

from __future__ import annotations

from pathlib import Path

from pressurepose.files import save_figure


def plot_realism(path: Path, real, sim, title: str) -> Path:
    """`real`, `sim`: eval.realism.FrameSet. The simulated mean image is shifted by the best
    along/across shifts of the profiles so that shapes, not placement, are compared."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pressurepose.eval.realism import COL_SHIFTS, ROW_SHIFTS, profile_similarity, shifted

    along, sr = profile_similarity(real.along, sim.along, ROW_SHIFTS)
    across, sc = profile_similarity(real.across, sim.across, COL_SHIFTS)
    img = shifted(shifted(sim.mean_image, sr, 0), sc, 1)  # as the profiles: zero-filled
    fig, ax = plt.subplots(1, 4, figsize=(14, 5.5), gridspec_kw={"width_ratios": [1, 1, 1.5, 1.5]})
    vmax = max(float(real.mean_image.max()), float(img.max()), 1e-9)
    for a, im, t in (
        (ax[0], real.mean_image, f"real mean ({real.n})"),
        (ax[1], img, f"simulated mean ({sim.n}), aligned"),
    ):
        a.imshow(im, vmin=0, vmax=vmax, cmap="viridis", aspect="auto")
        a.set_title(t)
        a.set_xlabel("column")
    ax[0].set_ylabel("row (head at 0)")
    ax[2].plot(real.along, label="real")
    ax[2].plot(shifted(sim.along, sr), label=f"simulated (shift {sr})")
    ax[2].set_title(f"along the bed: similarity {along:.2f}")
    ax[2].set_xlabel("row")
    ax[3].plot(real.across, label="real")
    ax[3].plot(shifted(sim.across, sc), label=f"simulated (shift {sc})")
    ax[3].set_title(f"across the bed: similarity {across:.2f}")
    ax[3].set_xlabel("column")
    for a in ax[2:]:
        a.set_ylabel("share of the force")
        a.legend()
    fig.suptitle(title)
    fig.tight_layout()
    out = save_figure(fig, Path(path), dpi=70)
    plt.close(fig)
    return out
