"""Training augmentations (`pressurepose train` flags): images moved along and across the bed,
mirrored left-right, re-pressed into other mattresses from their depth labels, read through
an air-cell mattress's transverse bands, the head resting on a pillow, and bands of rows
taken out (docs/network.md)."""

from __future__ import annotations

import dataclasses
import logging
import math

import torch

from pressurepose.body.joints import joint_index
from pressurepose.errors import UserError
from pressurepose.net.losses import Targets
from pressurepose.net.model import NetInputs
from pressurepose.net.preprocess import MAX_MMHG, gaussian_blur
from pressurepose.sim.mattress import PRESETS
from pressurepose.train.config import TrainConfig

log = logging.getLogger(__name__)


def shift_batch(
    inputs: NetInputs, targets: Targets, rows: int, cols: int, generator: torch.Generator | None
) -> tuple[NetInputs, Targets]:
    """Move every image of the batch by a random whole number of taxels (|dr| <= rows, |dc| <=
    cols) and its labels with it: the same body lying elsewhere on a uniform flat bed gives the
    same image moved (taxels leaving the grid are lost, those entering read 0 - as for a body
    partly off the mat). Real users lie wherever they lie; the generator's bodies do not cover
    every placement (PmatData's heads reach row 0)."""
    from pressurepose.maps import EMPTY_HEIGHT_M
    from pressurepose.mat import MatSpec

    p = inputs.pressure_mmhg
    B, R, C = p.shape
    draw = lambda n: torch.randint(-n, n + 1, (B,), generator=generator).tolist()  # noqa: E731
    dr, dc = draw(rows), draw(cols)

    def move(x: torch.Tensor, fill: float) -> torch.Tensor:
        out = torch.full_like(x, fill)
        for b, (r, c) in enumerate(zip(dr, dc)):
            out[b, max(r, 0) : R + min(r, 0), max(c, 0) : C + min(c, 0)] = x[
                b, max(-r, 0) : R + min(-r, 0), max(-c, 0) : C + min(-c, 0)
            ]
        return out

    mat = MatSpec()
    step = torch.tensor(
        [[mat.pitch_row_m * r, mat.pitch_col_m * c, 0.0] for r, c in zip(dr, dc)],
        dtype=targets.joints.dtype,
        device=targets.joints.device,
    )
    moved = Targets(
        joints=targets.joints + step[:, None],
        shape=targets.shape,
        depth_mm=None if targets.depth_mm is None else move(targets.depth_mm, 1000 * EMPTY_HEIGHT_M),
        contact=None if targets.contact is None else move(targets.contact, 0.0),
    )
    return dataclasses.replace(inputs, pressure_mmhg=move(p, 0.0)), moved


def mirror_batch(
    inputs: NetInputs, targets: Targets, share: float, generator: torch.Generator | None
) -> tuple[NetInputs, Targets]:
    """Mirror a random `share` of the images left-right (columns c -> 26 - c) with their labels:
    the joints reflected across the mat's centre line (y -> W - y, W the sensing width) with left
    and right swapped (J24_MIRROR); depth and contact maps flipped; the shape kept (the body
    model is symmetric to ~1 mm, tests/test_body.py). The bed and the simulation are mirror
    symmetric (a mirrored body gives the mirrored image, tests/test_sim.py), so the mirrored
    sample is a sample of the same generator - the one of the mirrored person."""
    from pressurepose.body.joints import mirror_joints
    from pressurepose.mat import MatSpec

    p = inputs.pressure_mmhg
    on = torch.rand(p.shape[0], generator=generator).to(p.device) < share
    if not bool(on.any()):
        return inputs, targets
    flip = lambda x: None if x is None else torch.where(on[:, None, None], x.flip(-1), x)  # noqa: E731
    j = targets.joints
    joints = torch.where(on[:, None, None], mirror_joints(j, MatSpec().sensing_width_m), j)
    return (
        dataclasses.replace(inputs, pressure_mmhg=flip(p)),
        Targets(joints=joints, shape=targets.shape, depth_mm=flip(targets.depth_mm), contact=flip(targets.contact)),
    )


# Re-press augmentation: ranges of the mattress law drawn per image (docs/model-history.md).
REPRESS_EXTRA_SINK_MM = (0.0, 40.0)  # delta: how much deeper a softer mattress lets the body in
REPRESS_EXPONENT = (0.5, 1.5)  # gamma: pressure ~ compression^gamma
REPRESS_SPREAD_TAXELS = (0.3, 1.0)  # sigma: the mat and cover's spread
# The sensor reads 0 below its floor: the generator's default bed's (the sponge preset's floor_mmhg,
# PmatData's 3.31 mmHg); a re-pressed image read down to ~1 mmHg would carry a halo no real frame has.
REPRESS_THRESHOLD_MMHG = PRESETS["sponge"]["floor_mmhg"]


def repress_batch(
    inputs: NetInputs, depth_mm: torch.Tensor, share: float, generator: torch.Generator | None
) -> NetInputs:
    """Replace a random `share` of the pressure images by the body pressed into another
    mattress: from the depth label Q (mm, < 0 where the body is sunk in), compression c =
    max(0, delta - Q) (delta ~ U(REPRESS_EXTRA_SINK_MM): a softer mattress lets the body in
    deeper), pressure ~ c^gamma (gamma ~ U(REPRESS_EXPONENT): from a softening to a stiffening
    law), spread by a Gaussian of sigma ~ U(REPRESS_SPREAD_TAXELS) taxels, scaled so the image
    keeps its total, then the sensor's threshold and 100 mmHg ceiling. The pose does not move
    (a first-order view of a softer bed). Why: real side-lying frames (PmatData C, D) carry
    nearly uniform pressure over the whole silhouette (0.36-0.42 m^2), simulated ones a few
    stiff blobs (0.25 m^2) - the calibrated foundation's cubic term and threshold - and the
    network read the blobs as the cue for lying on a side. Images not drawn are unchanged."""
    p = inputs.pressure_mmhg
    u = torch.rand(4, p.shape[0], generator=generator).to(p)
    delta, gamma = _uniform(REPRESS_EXTRA_SINK_MM, u[1]), _uniform(REPRESS_EXPONENT, u[2])
    c = (delta[:, None, None] - depth_mm.to(p)).clamp(min=0.0)
    q = gaussian_blur(c.pow(gamma[:, None, None]) * (c > 0), _uniform(REPRESS_SPREAD_TAXELS, u[3]))
    return _read_again(inputs, q, u[0] < share)


def _uniform(bounds: tuple[float, float], u: torch.Tensor) -> torch.Tensor:
    """U(bounds) from U(0, 1) draws u."""
    return bounds[0] + (bounds[1] - bounds[0]) * u


def _read_again(inputs: NetInputs, q: torch.Tensor, on: torch.Tensor) -> NetInputs:
    """The images `on` (B,) replaced by q (B, 64, 27) scaled to their total, then read as the
    sensor does (below REPRESS_THRESHOLD_MMHG: 0; ceiling MAX_MMHG); the others unchanged."""
    p = inputs.pressure_mmhg
    q = q * (p.sum((1, 2), keepdim=True) / q.sum((1, 2), keepdim=True).clamp(min=1e-9))
    q = torch.where(q >= REPRESS_THRESHOLD_MMHG, q, torch.zeros_like(q)).clamp(max=MAX_MMHG)
    return dataclasses.replace(inputs, pressure_mmhg=torch.where(on[:, None, None], q, p))


BANDS_PERIOD_ROWS = (2.0, 4.0)  # T: taxel rows per air cell
BANDS_DEPTH = (0.3, 1.0)  # a: how much the gain varies between a cell's crest and gap


def bands_batch(inputs: NetInputs, share: float, generator: torch.Generator | None) -> NetInputs:
    """Multiply a random `share` of the images by the pattern of an air-cell mattress: cells
    running across the bed, so the reading varies along it, gain(r) = max(0, 1 + a cos(2 pi (r -
    phi) / T)) per row r (T ~ U(BANDS_PERIOD_ROWS), a ~ U(BANDS_DEPTH), phi ~ U(0, T)); the total
    kept, then the sensor's threshold and ceiling. Alternating-pressure air mattresses, the
    usual hospital bed against pressure injuries, read in such bands (PmatData's air mattress:
    rows alternate bright and dark under the whole body); the foundation model of a uniform
    mattress cannot make them. Images not drawn are unchanged."""
    p = inputs.pressure_mmhg
    u = torch.rand(4, p.shape[0], generator=generator).to(p)
    T, a = _uniform(BANDS_PERIOD_ROWS, u[1]), _uniform(BANDS_DEPTH, u[2])
    phi = T * u[3]
    r = torch.arange(p.shape[1], dtype=p.dtype, device=p.device)
    gain = (1 + a[:, None] * torch.cos(2 * math.pi * (r[None] - phi[:, None]) / T[:, None])).clamp(min=0.0)
    return _read_again(inputs, p * gain[:, :, None], u[0] < share)


# Texture augmentation: log-normal gain sds drawn per image (docs/network.md "The sensor's texture").
TEXTURE_ROW_SD = (0.05, 0.35)  # per row (real frames: row log-gain sd 0.16 sponge, 0.33 air)
TEXTURE_TAXEL_SD = (0.05, 0.30)  # per taxel


def texture_batch(inputs: NetInputs, share: float, generator: torch.Generator | None) -> NetInputs:
    """Read a random `share` of the images through a mat of uneven gain: each row's gain
    exp(s_r z_r) and each taxel's exp(s_t z_rc) (z standard normal, s_r ~ U(TEXTURE_ROW_SD), s_t ~
    U(TEXTURE_TAXEL_SD)); the total kept, then the sensor's threshold and ceiling. A real mat's
    rows and taxels differ in gain (PmatData's rows: log-gain sd 0.16-0.33 about the smoothed
    reading); the simulation's sensor has one gain. Images not drawn are unchanged."""
    p = inputs.pressure_mmhg
    B, R, C = p.shape
    u = torch.rand(3, B, generator=generator).to(p)
    z_row = torch.randn(B, R, 1, generator=generator).to(p)
    z_taxel = torch.randn(B, R, C, generator=generator).to(p)
    s_row, s_taxel = _uniform(TEXTURE_ROW_SD, u[1]), _uniform(TEXTURE_TAXEL_SD, u[2])
    gain = torch.exp(s_row[:, None, None] * z_row + s_taxel[:, None, None] * z_taxel)
    return _read_again(inputs, p * gain, u[0] < share)


# Speckle augmentation: stray readings off the body (docs/network.md "Stray readings").
SPECKLE_PER_IMAGE = (0.0, 8.0)  # expected stray spots per image, drawn per image
SPECKLE_MMHG = (REPRESS_THRESHOLD_MMHG, 15.0)  # a stray taxel's reading, log-uniform
SPECKLE_PAIR = 0.3  # share of the spots that reach one neighbouring taxel


def speckle_batch(inputs: NetInputs, share: float, generator: torch.Generator | None) -> NetInputs:
    """Add stray readings to a random `share` of the images: each taxel starts a spot with
    probability n / (rows x cols) (n ~ U(SPECKLE_PER_IMAGE) spots expected per image), a share
    SPECKLE_PAIR of the spots reach one neighbour along or across the bed, and a spot's taxels
    read log-uniform in SPECKLE_MMHG; a taxel reads the larger of the body's reading and the
    spot's (on the body a spot is lost in its load). The labels stay. Why: a real mat reads small
    loads that are not the body - a sheet's fold, a cable, a pillow's corner, a taxel reading
    high - where the simulation reads exactly 0 off the body: PmatData's frames hold 1.8 (sponge)
    to 5.6 (air) detached components under 2% of the force per frame, mostly one or two taxels at
    3-13 mmHg, the simulated ones 0.8, of 6 taxels (a hand, a heel); a network that has never
    seen one reads a spot on the mat's last row as the body reaching there (a 1.72 m subject
    read 1.92 m; docs/real_data.md). Images not drawn are unchanged."""
    p = inputs.pressure_mmhg
    B, R, C = p.shape
    u = torch.rand(2, B, generator=generator).to(p)
    draws = torch.rand(3, B, R, C, generator=generator).to(p)
    starts = draws[0] < (_uniform(SPECKLE_PER_IMAGE, u[1]) / (R * C))[:, None, None]
    down = starts & (draws[1] < SPECKLE_PAIR / 2)
    right = starts & (draws[1] >= SPECKLE_PAIR / 2) & (draws[1] < SPECKLE_PAIR)
    spots = starts.clone()
    spots[:, 1:] |= down[:, :-1]
    spots[:, :, 1:] |= right[:, :, :-1]
    lo, hi = SPECKLE_MMHG
    reading = lo * (hi / lo) ** draws[2]
    on = (u[0] < share)[:, None, None] & spots
    return dataclasses.replace(inputs, pressure_mmhg=torch.where(on, torch.maximum(p, reading), p))


FLATTEN_GAMMA = (0.0, 1.0)  # the exponent: 0 = one pressure over the whole loaded outline


def flatten_batch(inputs: NetInputs, share: float, generator: torch.Generator | None) -> NetInputs:
    """Flatten the contrast of a random `share` of the images: each loaded taxel's reading p ->
    p^g (g ~ U(FLATTEN_GAMMA); g = 0 leaves one pressure over the loaded outline), the total
    kept, then the sensor's threshold and ceiling; the outline is the same. Why: a network
    reads a real supine frame made uniform on its loaded taxels as prone (`heat_line`'s epoch
    19: 99 of 159 supine frames; `benchmarks/real_probe.py`): the hypothesis was that real mats
    read more uniform pressure than the simulation. Refuted twice: a line trained with it read
    PmatData worse (docs/model-history.md "Session 37"), and the real frames' high pressures are
    above the simulated ones, not below (docs/realism.md, session 38). Images not drawn are
    unchanged."""
    p = inputs.pressure_mmhg
    u = torch.rand(2, p.shape[0], generator=generator).to(p)
    g = _uniform(FLATTEN_GAMMA, u[1])[:, None, None]
    q = torch.where(p > 0, p.clamp(min=1e-30) ** g, torch.zeros_like(p))
    return _read_again(inputs, q, u[0] < share)


SPREAD_TAXELS = (0.5, 2.0)  # sigma of the mat and cover's lateral spread, taxels
SPREAD_FLOOR_MMHG = (1.0, 4.0)  # the lowest reading a mat reports (PmatData's normalisation: ~3-4)


def spread_batch(inputs: NetInputs, share: float, generator: torch.Generator | None) -> NetInputs:
    """Read a random `share` of the images through a mat and cover that spread the load: a
    Gaussian of sigma ~ U(SPREAD_TAXELS) taxels, then readings below a floor ~
    U(SPREAD_FLOOR_MMHG) zeroed, the total kept, the ceiling. Why: a network trained on the
    simulator reads a spread image taller (the default model on `pp8k_rib`'s test split: +1.2 cm
    median height error as generated, +3.8 spread by 1 taxel, +5.2 by 1.5; docs/network.md
    "Diagnostics of the real-frame reading"), and real mats spread: PmatData's supine heads are
    8-12 taxels wide at >= 3 mmHg where the simulated ones are 5, its frames read +6 cm tall.
    How much a mat and its cover spread is a property of the bed the network will meet, not of
    the body. Measured (session 39, a fine-tune with a control): the air mattress's height bias
    -1.8 cm, the sponge's unchanged, 2.7 mm of MPJPE on simulated images; an option, off by
    default. Images not drawn are unchanged."""
    p = inputs.pressure_mmhg
    u = torch.rand(3, p.shape[0], generator=generator).to(p)
    q = gaussian_blur(p, _uniform(SPREAD_TAXELS, u[1]))
    floor = _uniform(SPREAD_FLOOR_MMHG, u[2])[:, None, None]
    q = torch.where(q >= floor, q, torch.zeros_like(q))
    q = q * (p.sum((1, 2), keepdim=True) / q.sum((1, 2), keepdim=True).clamp(min=1e-9))
    on = (u[0] < share) & (q.sum((1, 2)) > 0)
    return dataclasses.replace(inputs, pressure_mmhg=torch.where(on[:, None, None], q.clamp(max=MAX_MMHG), p))


# Pillow augmentation: ranges drawn per image (docs/network.md, "Real frames span the mat").
PILLOW_BEYOND_HEAD_M = (0.10, 0.45)  # its far edge beyond the head joint, toward the head end
PILLOW_PAST_NECK_M = (-0.03, 0.05)  # its near edge past the neck joint, toward the feet
PILLOW_WIDTH_M = (0.20, 0.40)
PILLOW_SHARE = (0.04, 0.10)  # of the image's force, spread over the pillow's footprint
PILLOW_HEAD_MOVED = (0.5, 1.0)  # share of the head's own imprint the pillow takes over
PILLOW_TEXTURE = 0.3  # log-normal sigma of the spread, per taxel
HEAD, NECK = joint_index("head"), joint_index("neck")


def pillow_batch(inputs: NetInputs, joints: torch.Tensor, share: float, generator: torch.Generator | None) -> NetInputs:
    """Rest the head of a random `share` of the images on a pillow: over a footprint from
    PILLOW_BEYOND_HEAD_M beyond the head joint to PILLOW_PAST_NECK_M past the neck (along the
    bed) and PILLOW_WIDTH_M wide around the head (across), a share f ~ U(PILLOW_HEAD_MOVED) of
    the head's own imprint is taken away and a share s ~ U(PILLOW_SHARE) of the image's force is
    spread instead, nearly flat (a Gaussian about the head, sigma the footprint's length along
    the bed and half its width across) times a log-normal texture; then the image is scaled to
    its total and read as the sensor does. Rows beyond the mat's head end are lost, as on a real
    mat. The labels do not move (the pillow's few centimetres of head lift are ignored).
    Why: PmatData's supine frames load a broad, low patch (10-12 taxels, ~30 cm across, 10-16
    mmHg; the simulated heads 5-6 taxels) from the mat's first row in 85-88% of the frames and
    span 1.01 of the subject's height (the simulated supine bodies: 34% and 0.91); a network
    trained without pillows reads such a patch as a longer body (heat_rib2 on its own test
    images with a pillow reaching row 0: +4.7 cm; docs/network.md). Images whose head is off
    the mat, or not drawn, are unchanged."""
    from pressurepose.maps import cell_centres
    from pressurepose.mat import MatSpec

    mat = MatSpec()
    p = inputs.pressure_mmhg
    B, R, C = p.shape
    u = torch.rand(6, B, generator=generator).to(p)
    texture = torch.exp(PILLOW_TEXTURE * torch.randn(B, R, C, generator=generator).to(p))
    head, neck = joints[:, HEAD, :2].to(p), joints[:, NECK, 0].to(p)
    top = head[:, 0] - _uniform(PILLOW_BEYOND_HEAD_M, u[1])
    bottom = neck + _uniform(PILLOW_PAST_NECK_M, u[2])
    half = _uniform(PILLOW_WIDTH_M, u[3]) / 2
    X, Y = cell_centres(mat, covered=False, dtype=p.dtype, device=p.device)  # the taxels' centres
    x, y = X[:, 0], Y[0]
    in_x = (x[None] >= top[:, None]) & (x[None] < bottom[:, None])  # (B, R)
    in_y = (y[None] - head[:, 1:2]).abs() < half[:, None]  # (B, C)
    inside = in_x[:, :, None] & in_y[:, None, :]
    sx, sy = (bottom - top).clamp(min=mat.pitch_row_m), half
    bump = (
        torch.exp(-0.5 * ((x[None] - head[:, :1]) / sx[:, None]) ** 2)[:, :, None]
        * torch.exp(-0.5 * ((y[None] - head[:, 1:2]) / sy[:, None]) ** 2)[:, None, :]
    )
    spread = bump * texture * inside
    mass = spread.sum((1, 2), keepdim=True)
    total = p.sum((1, 2), keepdim=True)
    f, s = _uniform(PILLOW_HEAD_MOVED, u[4]), _uniform(PILLOW_SHARE, u[5])
    q = torch.where(inside, p * (1 - f[:, None, None]), p) + spread / mass.clamp(min=1e-30) * (s[:, None, None] * total)
    on = (u[0] < share) & (mass[:, 0, 0] > 0)
    return _read_again(inputs, q, on)


# Occlusion augmentation: how many rows one band takes out (docs/network.md "Flip test, IK
# settings and occlusion").
OCCLUDE_ROWS = (2, 8)


def occlude_batch(inputs: NetInputs, share: float, generator: torch.Generator | None) -> NetInputs:
    """Zero one band of k ~ U{OCCLUDE_ROWS} consecutive rows in a random `share` of the images,
    its first row drawn uniformly from the first to the last loaded row (so it lies on the body:
    the head end, the trunk or the heels alike; a band past the mat's end is cut short); the
    labels stay. Why: a network trained without it reads PmatData's frames from a few bands -
    zeroing one band of 4 loaded rows of the real frames turned 9-54 right posture reads of 255
    wrong, depending on where (heat_tex; docs/network.md "Flip test, IK settings and
    occlusion") - so whatever a real band holds that the simulation does not (a pillow's edge,
    heels shaped otherwise) decides its answer. Empty images and images not drawn are unchanged."""
    p = inputs.pressure_mmhg
    B, R, _ = p.shape
    u = torch.rand(3, B, generator=generator).to(p)
    rows = torch.arange(R, device=p.device)
    loaded = p.sum(-1) > 0  # (B, R)
    first = torch.where(loaded, rows, R).amin(1)
    last = torch.where(loaded, rows, -1).amax(1)
    start = first + (u[1] * (last - first + 1).clamp(min=0)).floor().long()
    k = OCCLUDE_ROWS[0] + (u[2] * (OCCLUDE_ROWS[1] - OCCLUDE_ROWS[0] + 1)).floor().long()
    band = (rows[None] >= start[:, None]) & (rows[None] < (start + k)[:, None])  # (B, R)
    on = (u[0] < share) & loaded.any(1)
    q = torch.where((on[:, None] & band)[:, :, None], torch.zeros_like(p), p)
    return dataclasses.replace(inputs, pressure_mmhg=q)


def augment_batch(
    inputs: NetInputs, targets: Targets, cfg: TrainConfig, generator: torch.Generator | None
) -> tuple[NetInputs, Targets]:
    """A training batch through every augmentation `cfg` turns on, in a fixed order: where the
    body lies (shift, mirror), what bed it lies on (re-press, flatten, spread, pillow, bands), how
    the mat reads it (texture, stray readings), then a band taken out (occlude)."""
    if cfg.shift_rows or cfg.shift_cols:
        inputs, targets = shift_batch(inputs, targets, cfg.shift_rows, cfg.shift_cols, generator)
    if cfg.mirror > 0:
        inputs, targets = mirror_batch(inputs, targets, cfg.mirror, generator)
    if cfg.repress > 0:
        if targets.depth_mm is None:
            raise UserError("--repress needs the depth maps (depth_mm) of the training samples")
        inputs = repress_batch(inputs, targets.depth_mm, cfg.repress, generator)
    if cfg.flatten > 0:
        inputs = flatten_batch(inputs, cfg.flatten, generator)
    if cfg.spread > 0:
        inputs = spread_batch(inputs, cfg.spread, generator)
    if cfg.pillow > 0:
        inputs = pillow_batch(inputs, targets.joints, cfg.pillow, generator)
    if cfg.bands > 0:
        inputs = bands_batch(inputs, cfg.bands, generator)
    if cfg.texture > 0:
        inputs = texture_batch(inputs, cfg.texture, generator)
    if cfg.speckle > 0:
        inputs = speckle_batch(inputs, cfg.speckle, generator)
    if cfg.occlude > 0:
        inputs = occlude_batch(inputs, cfg.occlude, generator)
    return inputs, targets


__all__ = [
    "augment_batch",
    "bands_batch",
    "flatten_batch",
    "spread_batch",
    "mirror_batch",
    "occlude_batch",
    "pillow_batch",
    "repress_batch",
    "shift_batch",
    "speckle_batch",
    "texture_batch",
]
