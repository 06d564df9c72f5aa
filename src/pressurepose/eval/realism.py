"""How much simulated pressure images look like real ones: the realism metrics.

Pure numpy on (N, 64, 27) images in mmHg, row 0 at the head end (docs/realism.md):
- `frame_metrics`: contact area (m^2), mean contact pressure and peak (mmHg), coverage (the
  share of the rows between the first and last loaded row that carry >= 1% of the image's
  force), and load shares per body region.
- `extent_of_height`: the length of the loaded rows (from the first to the last row carrying at
  least `EXTENT_SHARE` of the image's force) over the subject's height; `high_pressure`: the
  99th percentile of the loaded taxels' readings (the peak without single-taxel outliers);
  `force_from_head_end`: the force's share in slices of the height counted from the load's
  first row (where the shoulders and buttocks lie relative to the head end's start).
- `profile_similarity`: force profiles along (row sums) or across (column sums) the bed, the
  mean over frames of unit-sum profiles, compared by 1 - L1 / 2 (1 = identical shapes, 0 =
  disjoint), best over integer shifts so that placement on the mat is not judged.
- `fit_bands`: transverse bands (an air mattress's tubes): each row's force over its 5-row moving
  average, minus 1, fitted over every frame with one cosine along the bed; its period (scanned
  over `BAND_PERIODS_M` unless given), amplitude and the position of a crest.
- Body regions are found in the image, the same way for real and simulated frames: the top of
  the head is the first loaded row from the head end, the subject's height (known) scales the
  anthropometric fractions of `REGIONS` along the bed, and the arms are the load beside the
  trunk (farther than `ARM_HALF_WIDTH_OF_HEIGHT` x height from the trunk's centre line).
"""

from __future__ import annotations

import dataclasses

import numpy as np

COVERAGE_SHARE = 0.01
EXTENT_SHARE = 0.002  # rows holding less of the force do not count towards the load's length
ROW_SHIFTS = 15
COL_SHIFTS = 8
# Body regions along the bed: (name, start, end) as fractions of the height from the top of
# the head (standing-height proportions, Drillis & Contini's segment lengths, rounded).
REGIONS: tuple[tuple[str, float, float], ...] = (
    ("head", 0.0, 0.13),
    ("shoulders", 0.13, 0.30),
    ("back", 0.30, 0.45),
    ("buttocks", 0.45, 0.58),
    ("thighs", 0.58, 0.75),
    ("calves", 0.75, 0.92),
    ("heels", 0.92, 1.10),
)
ARM_ROWS = (0.13, 0.55)  # arms at the sides lie beside the trunk, shoulders to hips
ARM_HALF_WIDTH_OF_HEIGHT = 0.09  # trunk half-width (~0.16 m at 1.78 m); beyond it: arms
REGION_NAMES = tuple(r[0] for r in REGIONS) + ("arms",)
BAND_PERIODS_M = np.arange(0.08, 0.1301, 0.0002)  # pitches scanned for transverse bands
BAND_SMOOTH_ROWS = 5  # the moving average the rows are compared with
BAND_MIN_SHARE = 0.005  # rows whose moving average holds less of the force are left out


def _check(images: np.ndarray, name: str = "images") -> np.ndarray:
    images = np.asarray(images, dtype=np.float64)
    if images.ndim == 2:
        images = images[None]
    if images.ndim != 3:
        raise ValueError(f"{name} must have shape (N, rows, cols), got {images.shape}")
    if not np.isfinite(images).all() or (images < 0).any():
        raise ValueError(f"{name} must be finite and >= 0")
    return images


def coverage(image: np.ndarray, share: float = COVERAGE_SHARE) -> float:
    """Share of the rows from the first to the last loaded row that carry >= `share` of the
    image's force (0 for an empty image)."""
    rows = np.asarray(image, dtype=np.float64).sum(1)
    total = rows.sum()
    loaded = np.nonzero(rows > 0)[0]
    if total <= 0 or loaded.size == 0:
        return 0.0
    span = rows[loaded[0] : loaded[-1] + 1]
    return float((span >= share * total).mean())


def load_span(image: np.ndarray, share: float) -> tuple[int, int] | None:
    """The first and last row holding >= `share` of the image's force (None for an empty image)."""
    rows = np.asarray(image, dtype=np.float64).sum(1)
    total = rows.sum()
    if total <= 0:
        return None
    kept = np.nonzero(rows >= share * total)[0]
    return int(kept[0]), int(kept[-1])


def extent_of_height(image: np.ndarray, height_m: float, pitch_row_m: float, share: float = EXTENT_SHARE) -> float:
    """Length (m) from the first to the last row carrying >= `share` of the image's force, over
    `height_m` (0 for an empty image). A real frame whose load runs off the mat's end reads
    short."""
    span = load_span(image, share)
    return 0.0 if span is None else float((span[1] - span[0] + 1) * pitch_row_m / height_m)


def area_by_part_of_length(image: np.ndarray, parts: int = 10, share: float = EXTENT_SHARE) -> np.ndarray:
    """(parts,) loaded taxels in each of `parts` equal slices of the load's length (the rows from
    the first to the last holding >= `share` of the force; a slice boundary falls at the nearest
    row edge): where along the body the contact lies, whatever the body's height and place.
    Zeros for an empty image."""
    out = np.zeros(parts)
    span = load_span(image, share)
    if span is None:
        return out
    edges = np.rint(np.linspace(span[0], span[1] + 1, parts + 1)).astype(int)
    loaded = (np.asarray(image) > 0).sum(1)
    for i in range(parts):
        out[i] = loaded[edges[i] : edges[i + 1]].sum()
    return out


HEAD_END_BINS = 12  # slices of HEAD_END_WIDTH of the height: the head end to past the buttocks
HEAD_END_WIDTH = 0.05


def force_from_head_end(
    image: np.ndarray,
    height_m: float,
    pitch_row_m: float,
    bins: int = HEAD_END_BINS,
    width: float = HEAD_END_WIDTH,
    share: float = EXTENT_SHARE,
) -> np.ndarray:
    """(bins,) share of the image's force in each slice of `width` x the subject's height along the
    bed, measured from the load's first row (the first holding >= `share` of the force; a row
    belongs to the slice its centre falls in): where the shoulders and buttocks lie relative to
    the head end's start, in fractions of the body. Zeros for an empty image."""
    out = np.zeros(bins)
    span = load_span(image, share)
    if span is None:
        return out
    rows = np.asarray(image, dtype=np.float64).sum(1)
    at = (np.arange(rows.size) - span[0] + 0.5) * pitch_row_m / height_m / width  # slice coordinate
    keep = (at >= 0) & (at < bins)
    np.add.at(out, np.floor(at[keep]).astype(int), rows[keep])
    return out / rows.sum()


def high_pressure(image: np.ndarray, q: float = 0.99) -> float:
    """The `q` quantile of the loaded taxels' readings (0 for an empty image)."""
    img = np.asarray(image, dtype=np.float64)
    loaded = img[img > 0]
    return float(np.quantile(loaded, q)) if loaded.size else 0.0


def reading_floor(images: np.ndarray) -> float:
    """The lowest reading a set of frames reports: the median over frames of each frame's lowest
    loaded reading (PmatData's normalisation zeroes raw readings within 20 units of the empty
    level: 3.0-3.8 mmHg per set; the simulated sensor reads down to ~1 mmHg)."""
    imgs = _check(images)
    lows = [float(im[im > 0].min()) for im in imgs if (im > 0).any()]
    return float(np.median(lows)) if lows else 0.0


def read_with_floor(images: np.ndarray, floor_mmhg: float) -> np.ndarray:
    """Images read by a sensor that reports nothing below `floor_mmhg`: lower readings zeroed,
    each image scaled back to its force (a mat whose readings are normalised to the subject's
    weight, as real frames are). Compares simulated frames with real ones read that way."""
    imgs = np.asarray(images, dtype=np.float64)
    kept = np.where(imgs >= floor_mmhg, imgs, 0.0)
    total, left = imgs.sum((1, 2), keepdims=True), kept.sum((1, 2), keepdims=True)
    return np.where(left > 0, kept * total / np.where(left > 0, left, 1.0), imgs)


def region_shares(image: np.ndarray, height_m: float, pitch_row_m: float, pitch_col_m: float) -> dict[str, float]:
    """Share of the image's force in each body region (`REGIONS` along the bed, `arms` beside
    the trunk; the along-bed regions exclude what is counted as arms). Sums to 1."""
    img = np.asarray(image, dtype=np.float64)
    total = img.sum()
    out = dict.fromkeys(REGION_NAMES, 0.0)
    if total <= 0:
        return out
    rows = np.nonzero(img.sum(1) > 0)[0]
    top = rows[0]
    # row index -> fraction of the height from the head top (row centres)
    frac = (np.arange(img.shape[0]) - top + 0.5) * pitch_row_m / height_m
    arm_rows = (frac >= ARM_ROWS[0]) & (frac < ARM_ROWS[1])
    trunk = img[arm_rows]
    cols = np.arange(img.shape[1])
    centre = (trunk.sum(0) * cols).sum() / trunk.sum() if trunk.sum() > 0 else (img.shape[1] - 1) / 2
    beside = np.abs(cols - centre) * pitch_col_m > ARM_HALF_WIDTH_OF_HEIGHT * height_m
    arms = np.zeros_like(img, dtype=bool)
    arms[np.ix_(arm_rows, beside)] = True
    out["arms"] = float(img[arms].sum() / total)
    rest = np.where(arms, 0.0, img)
    for k, (name, a, b) in enumerate(REGIONS):
        # the first and last regions are open-ended: nothing loaded falls outside the body
        lo = -np.inf if k == 0 else a
        hi = np.inf if k == len(REGIONS) - 1 else b
        out[name] = float(rest[(frac >= lo) & (frac < hi)].sum() / total)
    return out


@dataclasses.dataclass(frozen=True)
class FrameSet:
    """Summary of a set of frames: medians over frames, mean unit-sum profiles."""

    n: int
    area_m2: float
    mean_mmhg: float
    peak_mmhg: float
    p99_mmhg: float  # median over frames of `high_pressure`
    extent: float  # median over frames of `extent_of_height`
    coverage: float
    regions: dict[str, float]  # mean share per region
    area_tenths: np.ndarray  # (10,) mean over frames of `area_by_part_of_length` (taxels)
    head_end: np.ndarray  # (HEAD_END_BINS,) mean over frames of `force_from_head_end`
    along: np.ndarray  # (rows,) mean unit-sum row profile
    across: np.ndarray  # (cols,)
    mean_image: np.ndarray  # (rows, cols) mean image (mmHg)


def summarise(images: np.ndarray, heights_m: np.ndarray, pitch_row_m: float, pitch_col_m: float) -> FrameSet:
    """Metrics of N frames (mmHg, (N, rows, cols)) of subjects of the given heights (N,)."""
    images = _check(images)
    heights = np.broadcast_to(np.asarray(heights_m, dtype=np.float64), (images.shape[0],))
    if images.shape[0] == 0:
        raise ValueError("no frames to summarise")
    if not (np.isfinite(heights).all() and (heights > 0).all()):
        raise ValueError("the subjects' heights must be finite and > 0 m")
    sums = images.sum((1, 2))
    if (sums <= 0).any():
        raise ValueError(f"{int((sums <= 0).sum())} frame(s) carry no load")
    area = (images > 0).sum((1, 2)) * pitch_row_m * pitch_col_m
    mean = np.array([im[im > 0].mean() for im in images])
    regions = [region_shares(im, h, pitch_row_m, pitch_col_m) for im, h in zip(images, heights)]
    return FrameSet(
        n=images.shape[0],
        area_m2=float(np.median(area)),
        mean_mmhg=float(np.median(mean)),
        peak_mmhg=float(np.median(images.max((1, 2)))),
        p99_mmhg=float(np.median([high_pressure(im) for im in images])),
        extent=float(np.median([extent_of_height(im, h, pitch_row_m) for im, h in zip(images, heights)])),
        coverage=float(np.mean([coverage(im) for im in images])),
        regions={k: float(np.mean([r[k] for r in regions])) for k in REGION_NAMES},
        area_tenths=np.mean([area_by_part_of_length(im) for im in images], 0),
        head_end=np.mean([force_from_head_end(im, h, pitch_row_m) for im, h in zip(images, heights)], 0),
        along=_mean_profile(images.sum(2)),
        across=_mean_profile(images.sum(1)),
        mean_image=images.mean(0),
    )


def _mean_profile(profiles: np.ndarray) -> np.ndarray:
    unit = profiles / profiles.sum(1, keepdims=True)
    m = unit.mean(0)
    return m / m.sum()


def shifted(values: np.ndarray, shift: int, axis: int = 0) -> np.ndarray:
    """`values` moved by `shift` bins along `axis` (positive: towards higher indices),
    zero-filled."""
    values = np.asarray(values)
    out = np.zeros_like(values)
    n = values.shape[axis]
    if abs(shift) >= n:
        return out
    src = [slice(None)] * values.ndim
    dst = [slice(None)] * values.ndim
    src[axis], dst[axis] = (
        (slice(0, n - shift), slice(shift, n)) if shift >= 0 else (slice(-shift, n), slice(0, n + shift))
    )
    out[tuple(dst)] = values[tuple(src)]
    return out


def profile_similarity(a: np.ndarray, b: np.ndarray, max_shift: int) -> tuple[float, int]:
    """Best 1 - L1/2 between unit-sum profiles a and b over shifts of b in [-max_shift,
    max_shift], and that shift. Profiles are renormalised to unit sum first."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"profiles must be 1-D of the same length, got {a.shape} and {b.shape}")
    if not (a.sum() > 0 and b.sum() > 0):
        raise ValueError("profiles must carry load")
    a, b = a / a.sum(), b / b.sum()
    best, best_shift = -1.0, 0
    for s in range(-max_shift, max_shift + 1):
        sim = 1.0 - 0.5 * np.abs(a - shifted(b, s)).sum()
        if sim > best + 1e-12:
            best, best_shift = sim, s
    return float(best), best_shift


def band_ratios(images: np.ndarray) -> np.ndarray:
    """(N, rows): each row's force over its `BAND_SMOOTH_ROWS`-row moving average, minus 1 (NaN
    where that average holds less than `BAND_MIN_SHARE` of the frame's force, and in the rows
    the average does not cover fully)."""
    images = _check(images)
    rows = images.sum(2)
    rows = rows / np.maximum(rows.sum(1, keepdims=True), 1e-300)
    k = BAND_SMOOTH_ROWS
    smooth = np.stack([np.convolve(r, np.ones(k) / k, mode="same") for r in rows])
    ok = smooth >= BAND_MIN_SHARE
    ok[:, : k // 2] = ok[:, rows.shape[1] - k // 2 :] = False
    return np.where(ok, rows / np.where(ok, smooth, 1.0) - 1.0, np.nan)


@dataclasses.dataclass(frozen=True)
class Bands:
    """A cosine fitted to `band_ratios` along the bed."""

    period_m: float
    amplitude: float
    crest_m: float  # x of a crest (mat frame, row 0's head edge at 0), in [0, period)
    r2: float  # share of the ratios' variance about 0 the cosine explains


def fit_bands(images: np.ndarray, pitch_row_m: float, period_m: float | None = None) -> Bands:
    """Least-squares cosine through the row ratios of all frames (`band_ratios`), at `period_m` or
    at the best of `BAND_PERIODS_M`."""
    ratios = band_ratios(images)
    known = ~np.isnan(ratios)
    if known.sum() < 3:
        raise ValueError("too few loaded rows to fit bands")
    x = (np.nonzero(known)[1] + 0.5) * pitch_row_m
    y = ratios[known]
    best = None
    for period in [period_m] if period_m is not None else BAND_PERIODS_M:
        phase = 2 * np.pi * x / period
        A = np.stack([np.cos(phase), np.sin(phase)], 1)
        coef = np.linalg.lstsq(A, y, rcond=None)[0]
        r2 = 1.0 - float(((y - A @ coef) ** 2).sum() / max((y**2).sum(), 1e-300))
        if best is None or r2 > best[0]:
            best = (r2, float(period), coef)
    r2, period, (a, b) = best
    crest = (np.arctan2(b, a) / (2 * np.pi) * period) % period
    return Bands(period_m=period, amplitude=float(np.hypot(a, b)), crest_m=float(crest), r2=r2)


@dataclasses.dataclass(frozen=True)
class Comparison:
    along: float
    across: float
    shift_rows: int
    shift_cols: int
    area_ratio: float  # b / a
    coverage_ratio: float  # b / a


def compare(a: FrameSet, b: FrameSet) -> Comparison:
    """b against a (a is the reference: real frames)."""
    along, sr = profile_similarity(a.along, b.along, ROW_SHIFTS)
    across, sc = profile_similarity(a.across, b.across, COL_SHIFTS)
    return Comparison(
        along=along,
        across=across,
        shift_rows=sr,
        shift_cols=sc,
        area_ratio=b.area_m2 / a.area_m2 if a.area_m2 > 0 else float("nan"),
        coverage_ratio=b.coverage / a.coverage if a.coverage > 0 else float("nan"),
    )


__all__ = [
    "EXTENT_SHARE",
    "read_with_floor",
    "reading_floor",
    "Bands",
    "Comparison",
    "FrameSet",
    "REGIONS",
    "REGION_NAMES",
    "band_ratios",
    "compare",
    "coverage",
    "extent_of_height",
    "fit_bands",
    "force_from_head_end",
    "HEAD_END_BINS",
    "HEAD_END_WIDTH",
    "high_pressure",
    "load_span",
    "profile_similarity",
    "region_shares",
    "shifted",
    "summarise",
]
