"""Dataset partitions of seed Table 4 as named presets, and the cells that spread the limbs.

A partition fixes the root distribution (roll, yaw, shift), which stratification cells each
limb may be asked to reach, and extra conditions (hands behind the head, crossed feet,
straight knees and elbows). Gender and the over-the-bed flag are chosen alongside it
(`SamplingConfig`), as Table 4 splits every partition by both.

Cells (seed A.1, Fig. 10; cell layout as in the original generator). They live in the bed's
axes after the root roll and yaw (x along the bed toward the foot, z up), so "height" is the
height above the bed whatever way the body lies:
- legs: the ankle may not lie above the hip (toward the head); its drop below the hip along
  the bed, d in [0, L] with L = the leg's rest length hip-knee-ankle, is split into 4 cells of
  L / 4 (the last one open-ended);
- arms: the wrist's offset from the shoulder toward the head, o in [-A, A] with A = the arm's
  rest length shoulder-elbow-wrist, is split into 8 cells of A / 4 (cell 0 = highest, the two
  outer cells open-ended);
- every distal joint (ankle, wrist) starts within +-10 cm of its proximal joint's height.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

from pressurepose.errors import UserError

LEG_CELLS = 4
ARM_CELLS = 8
HEIGHT_TOLERANCE_M = 0.10  # seed A.1: distal joint within +-10 cm of the proximal joint's height
HOLD_ROLL_M = 0.5  # lateral_straight's trunk roll hold: 0.5 m x weight per radian (docs/sampling.md)
GENDERS = ("female", "male")
# Failed attempts per shape and root over the bed for the partitions whose limbs fail often
# there (hands behind the head, crossed legs, straight limbs; issue 21, docs/sampling.md).
OVER_BED_MAX_FAILURES = 5


# The sampling law's version, pinned by generated datasets (generate.json): a dataset drawn
# under another law does not resume. 1: up to 2026-11-25; 2: knees and elbows no lower than
# HEIGHT_TOLERANCE_M below their hip or shoulder, face-down bodies' legs in the far cells, a
# sample's roll kept across its shapes (docs/sampling.md "Face-down bodies do not kneel"), and
# over the bed OVER_BED_MAX_FAILURES attempts per shape where limbs fail often; 3: Anny's weight
# phenotype drawn with a density rising linearly (`body.shape_ranges.ANNY_POWERS`; docs/sampling.md
# "An adult population's body mass"); 4: half_sitting's hips 0.2-0.5 m past the hinge, not 0.05-0.3
# (docs/sampling.md "Half-sitting on a raised bed"); 5: half_sitting over the bed measures the arms'
# over-bed rule on the head section as they will lie once sat up, and finds the trunk's pitch by
# grids instead of a bisection (session 48; the other partitions' samples unchanged, bit for bit);
# 6: the tilted partition's legs in cell 3 and wrists in cells 4-7 (session 59; first drawn with
# legs in cells 2-3 and wrists in 3-6; the other partitions' samples unchanged).
SAMPLING_LAW = 6


@dataclasses.dataclass(frozen=True)
class Partition:
    """One row group of seed Table 4 (angles in radians, lengths in metres)."""

    name: str
    description: str
    roll: tuple[float, float]  # root roll about the bed's long axis, uniform
    either_side: bool = False  # the drawn roll's sign at random (left or right side)
    yaw: tuple[float, float] = (-math.pi / 6, math.pi / 6)  # in the bed plane, uniform
    shift_x: tuple[float, float] = (-0.2, 0.2)  # pelvis along the bed from the mattress centre
    shift_y: tuple[float, float] = (-0.2, 0.2)  # pelvis across the bed
    leg_cells: tuple[int, ...] = tuple(range(LEG_CELLS))
    arm_cells: tuple[int, ...] = tuple(range(ARM_CELLS))
    over_bed_arm_cells: tuple[int, ...] | None = None  # arm cells over the bed (None: arm_cells)
    # Failed attempts per shape and root over the bed (None: SamplingConfig.max_failures, the
    # seed's 20; the smaller of the two applies). Issue 21: where the limbs often fail over the
    # bed, most attempts went to shapes and roots that fail every one (docs/sampling.md).
    over_bed_max_failures: int | None = None
    hands_behind_head: bool = False
    crossed_legs: bool = False
    straight_limbs: bool = False
    # Capsules checked for self-collision (seed A.1); the hands may touch the head when they
    # rest behind it, so that partition leaves them out, as the original did.
    checked_capsules: tuple[str, ...] = tuple(
        f"{s}_{p}" for s in ("left", "right") for p in ("hand", "forearm", "foot", "calf")
    )
    over_bed_choices: tuple[bool, ...] = (False, True)  # Table 4 rows that exist
    # Head-of-bed angles (deg) drawn per sample; (0,) = the flat bed. On a raised bed the body
    # is sat up after its limbs are drawn (sampling.sitting), and shift_x places the midpoint
    # of the hip joints relative to the hinge (positive: toward the foot) instead of the pelvis
    # relative to the mattress centre.
    head_angles_deg: tuple[float, ...] = (0.0,)
    # Sim #1's trunk roll hold for this partition (SettleConfig.hold_roll_m; 0: passive body).
    hold_roll_m: float = 0.0
    # A wedge under each body's back in the articulated rest (`sim.wedge`; its slope the body's turn).
    wedge: bool = False

    @property
    def raised(self) -> bool:
        return any(a > 0 for a in self.head_angles_deg)


def _partitions() -> dict[str, Partition]:
    no_hands = tuple(f"{s}_{p}" for s in ("left", "right") for p in ("forearm", "foot", "calf"))
    parts = [
        Partition("general", "any roll, even leg and arm space", roll=(-math.pi, math.pi)),
        Partition("supine", "supine general: on the back, even leg and arm space", roll=(0.0, 0.0)),
        Partition(
            "hands_behind_head",
            "supine, even leg space, both hands behind the head (Fig. 10b)",
            roll=(0.0, 0.0),
            arm_cells=(0, 1, 2, 3),
            hands_behind_head=True,
            over_bed_max_failures=OVER_BED_MAX_FAILURES,
            checked_capsules=no_hands,
            over_bed_choices=(True,),
        ),
        Partition(
            "prone_hands_up",
            "prone, even leg space, hands above the shoulders",
            roll=(math.pi, math.pi),
            arm_cells=(0, 1, 2, 3),
            over_bed_choices=(True,),
        ),
        # Crossed feet cannot be near the buttocks (leg cell 0: no solution in 1e5 draws).
        Partition(
            "crossed_legs",
            "supine, even leg and arm space, feet crossed (left ankle right of the right)",
            roll=(0.0, 0.0),
            leg_cells=(1, 2, 3),
            crossed_legs=True,
            over_bed_max_failures=OVER_BED_MAX_FAILURES,
        ),
        # A straight leg held within 10 cm of the hip's height ends more than 3/4 of its length
        # below the hip (hip abduction <= 38.6 deg), so only the last leg cell is reachable.
        # Over the bed, a straight arm held out sideways - cells 3 to 5, wrist between A/2
        # toward the feet and A/4 toward the head of the shoulder, so >= 0.87 A across the body -
        # has its hand off the mattress when it points outward and crosses the torso when it
        # points inward, for most bodies and roots (docs/sampling.md: reached for 9-13% of male
        # and 21-62% of female body and root draws): those cells are not drawn there.
        Partition(
            "straight_limbs",
            "supine, knees and elbows straight, even arm space",
            roll=(0.0, 0.0),
            leg_cells=(LEG_CELLS - 1,),
            straight_limbs=True,
            over_bed_arm_cells=(0, 1, 2, 6, 7),
            over_bed_max_failures=OVER_BED_MAX_FAILURES,
        ),
        # Beyond Table 4 (seed A.2: sitting poses on a bent bed). PmatData group F's subjects
        # rest with the buttocks 6-19 taxel rows (0.17-0.54 m) foot-ward of the hinge at
        # angles of 0-60 deg in steps of 10; the yaw stays small, as a sitting person's. The
        # hips 0.2-0.5 m past the hinge since sampling law 4: the articulated rest matches group
        # F's centres of pressure with them 0.32-0.50 m past it (docs/realism.md "Raised beds").
        Partition(
            "half_sitting",
            "supine, half-sitting in a bed with the head section raised 10-60 deg, even leg and arm space",
            roll=(0.0, 0.0),
            yaw=(-math.pi / 18, math.pi / 18),
            shift_x=(0.2, 0.5),
            shift_y=(-0.15, 0.15),
            head_angles_deg=(10.0, 20.0, 30.0, 40.0, 50.0, 60.0),
            # Over the bed, a hand raised above the head (arm cells 0, 1) passes the
            # head end of the short raised section (0.52 m of mattress above the hinge).
            over_bed_arm_cells=(2, 3, 4, 5, 6, 7),
        ),
        # Beyond Table 4: side-lying as people rest on a side (PmatData groups C and D, SLP's
        # lateral postures): the roll within 20 deg of a side, the ankles at most 3/4 of the leg
        # below the hips (hips and knees bent; a body on its side with straight legs rolls onto
        # its front or back in sim #1), the wrists between above the shoulder and the waist.
        Partition(
            "lateral",
            "on the left or right side, hips and knees bent, arms in front",
            roll=(math.pi / 2 - math.pi / 9, math.pi / 2 + math.pi / 9),
            either_side=True,
            yaw=(-math.pi / 18, math.pi / 18),
            leg_cells=(1, 2, 3),
            arm_cells=(2, 3, 4, 5),
        ),
        # Beyond Table 4: side-lying with the legs nearly straight (ankles more than 3/4 of the
        # leg below the hips), as PmatData's side-lying subjects lie. A passive body in that
        # pose rolls onto its front or back, so sim #1 holds the trunk's roll (a person's muscle
        # tone; SettleConfig.hold_roll_m) while the limbs settle.
        Partition(
            "lateral_straight",
            "on the left or right side, legs nearly straight, arms in front (trunk roll held in sim #1)",
            roll=(math.pi / 2 - math.pi / 9, math.pi / 2 + math.pi / 9),
            either_side=True,
            yaw=(-math.pi / 18, math.pi / 18),
            leg_cells=(LEG_CELLS - 1,),
            arm_cells=(2, 3, 4, 5),
            hold_roll_m=HOLD_ROLL_M,
        ),
        # Beyond Table 4: turned 15-45 deg toward a side with a wedge under the back, as people
        # are positioned to offload the sacrum (PmatData group E: 20 and 40 deg, legs straight,
        # arms down); the articulated rest props each body on a wedge sloped at its turn
        # (`sim.wedge`, `articulated_config_for`).
        Partition(
            "tilted",
            "turned 15-45 deg toward the left or right on a wedge under the back, legs nearly straight, wrists below the shoulders",
            roll=(math.pi / 12, math.pi / 4),
            either_side=True,
            yaw=(-math.pi / 18, math.pi / 18),
            leg_cells=(LEG_CELLS - 1,),
            arm_cells=(4, 5, 6, 7),
            wedge=True,
        ),
    ]
    return {p.name: p for p in parts}


PARTITIONS: dict[str, Partition] = _partitions()


def get_partition(name: str) -> Partition:
    """A partition by name; ValueError listing the valid names otherwise."""
    try:
        return PARTITIONS[name]
    except KeyError:
        raise UserError(f"unknown partition {name!r}; valid partitions: {', '.join(PARTITIONS)}") from None


@dataclasses.dataclass(frozen=True)
class SamplingConfig:
    """Which initial poses to draw.

    Attributes:
        partition: general, supine, hands_behind_head, prone_hands_up, crossed_legs,
            straight_limbs, half_sitting (head of the bed raised 10-60 deg), lateral (on either
            side, legs drawn up), lateral_straight (on either side, legs nearly straight; the
            trunk roll held in sim #1) or tilted (turned 15-45 deg on a wedge; the articulated
            engine).
        gender: Gender of the sampled bodies.
        over_bed: Keep knees, ankles, feet, elbows, wrists and hands over the mattress.
        seed: dataset seed; a sample is a function of (seed, partition, gender, over_bed, index).
        max_failures: failed pose attempts (a limb that cannot reach its cell, or a self
            collision) before the shape and root are drawn again (seed: 20; over the bed, a
            partition's `over_bed_max_failures` caps it: 5 for hands behind the head, crossed
            legs and straight limbs).
        max_shapes: shapes tried per sample before giving up with an error (50: the hardest
            partition, straight limbs over the bed, needed 14 shape resamples for 2 male samples
            in 2,048 - at most 17 in 2,048 with 5 attempts per shape - and that count's tail
            falls ~2x per extra shape; more is stopped).
        max_limb_draws: joint-angle draws per limb and attempt before it counts as a failure.
    """

    partition: str = "general"
    gender: Literal["female", "male"] = "female"
    over_bed: bool = False
    seed: int = 0
    max_failures: int = 20
    max_shapes: int = 50
    max_limb_draws: int = 16384

    def __post_init__(self) -> None:
        part = get_partition(self.partition)
        if self.gender not in GENDERS:
            raise UserError(f"unknown gender {self.gender!r}; expected one of {', '.join(GENDERS)}")
        if self.over_bed not in part.over_bed_choices:
            raise UserError(
                f"partition {self.partition!r} exists only with over_bed={part.over_bed_choices[0]} (seed Table 4)"
            )
        for name in ("max_failures", "max_shapes", "max_limb_draws"):
            if getattr(self, name) < 1:
                raise UserError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.seed < 0:
            raise UserError(f"seed must be >= 0, got {self.seed}")

    @property
    def spec(self) -> Partition:
        return get_partition(self.partition)


def max_failures(partition: Partition, config: SamplingConfig) -> int:
    """Failed attempts a shape and root get before they are drawn again: the config's
    `max_failures`, capped over the bed by the partition's `over_bed_max_failures`."""
    cap = partition.over_bed_max_failures if config.over_bed else None
    return config.max_failures if cap is None else min(config.max_failures, cap)


def limb_cells(partition: Partition, over_bed: bool) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """(leg cells, arm cells) a partition draws from, with or without the bed outline."""
    arms = (
        partition.over_bed_arm_cells if (over_bed and partition.over_bed_arm_cells is not None) else partition.arm_cells
    )
    return partition.leg_cells, arms


# Bodies whose front faces the bed within 30 deg: their legs draw only the far cells (ankle at
# least half the leg's length below the hip along the body). Measured with the knee rule of
# `limb_draws`, 1,024 flat general samples: beyond 165 deg cells 0 and 1 ended in 6 of 162 legs
# (the others redrawn after failing two shapes), 150-165 deg cell 0 in 24 of 184 (docs/sampling.md).
FACE_DOWN_ROLL_RAD = math.radians(150.0)
FACE_DOWN_LEG_CELLS = (2, 3)
FACE_DOWN_LEG_CELLS_OVER_BED = (3,)


def leg_cells_for_roll(leg_cells: tuple[int, ...], roll: float, over_bed: bool) -> tuple[int, ...]:
    """The leg cells a body rolled by `roll` (rad) may draw: face down (|roll| beyond
    FACE_DOWN_ROLL_RAD) only the far ones - nearer the buttocks its knee would be pressed into
    the bed - and all of the partition's otherwise (or if it has no far one)."""
    if abs(roll) <= FACE_DOWN_ROLL_RAD:
        return leg_cells
    far = FACE_DOWN_LEG_CELLS_OVER_BED if over_bed else FACE_DOWN_LEG_CELLS
    return tuple(c for c in leg_cells if c in far) or leg_cells
