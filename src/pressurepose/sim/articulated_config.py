"""Settings of the articulated sim #2 (`sim.articulated.rest_articulated`; defaults and their
measurements: docs/physics.md, docs/realism.md)."""

from __future__ import annotations

import dataclasses
import math

from pressurepose.body.joints import J24_NAMES
from pressurepose.errors import UserError
from pressurepose.sim.pillow import Pillow
from pressurepose.sim.wedge import Wedge


@dataclasses.dataclass(frozen=True)
class ArticulatedConfig:
    """Settings of the articulated rest (defaults: docs/physics.md)."""

    stiffness_scale: float = 0.8
    """Multiplies every joint's seed stiffness (1 = sim #1's springs). 0.8 since session 42, with the
    mat's membrane: the membrane gives the contact area the relaxed 0.5 had bought (the side-lying
    area was 10-14% short with 1), and the stiffer legs carry the supine calves' and heels' share
    (docs/realism.md "Stiffer joints with the membrane")."""
    neck_stiffness_scale: float = 0.2
    """Extra factor on the neck and head springs (a relaxed neck lets the head rest): with
    `stiffness_scale` 0.8, 0.16 x the seed's neck."""
    lying_extension: tuple[tuple[str, float], ...] = ()
    """(J24 joint, rad): how far a body on its back extends each joint - the head let back onto
    the bed, the back flattened (`articulation.lying_reference`): the springs' rest pose, not
    their stiffness."""
    spine_stiffness_scale: float = 1.1
    """Extra factor on the spine's springs (spine1-3)."""
    spine_lateral_scale: float = 1.0
    """Extra factor on the spine's sideways bending (its DoF about the bed's cross axis on a
    body lying on its side; blended by the body's roll, `articulation.joint_stiffness`)."""
    outer: int = 24
    """Re-posings of the mesh at most (each re-linearises the kinematics; friction's sliding
    and a side-lying body's roll need more than 10 to finish; 20 since session 42, 14 before:
    on the air preset's nearly flat top the parts keep sliding a few re-posings longer; 24 since
    session 49: 16 on the coarse grid and 8 on the image's; on the paper mix 0.224 of the samples
    end at the cap against the one-grid engine's 0.266 with 20, though straight limbs 0.12 against
    0.07). Every body takes all the coarse ones; on the image's grid a settled body stops early,
    so only the slow ones pay for the rest."""
    damp_swings: bool = True
    """A re-posing whose motion reverses an unknown's last one takes only the secant share of it
    (`rest_state.damp_swings`), so an elbow or a hip swinging about a contact's onset settles
    instead of alternating to the cap (session 46: bodies still moving at the cap 23 / 31 / 31
    -> 15 / 14 / 25 of 64, supine / general / lateral_straight, docs/realism.md). False: every
    re-posing takes its whole motion (engine revision 6)."""
    inner: int = 25
    """Newton steps of the last linearisation (the rest itself)."""
    inner_reposing: int = 6
    """Newton steps of the linearisations before each re-posing."""
    reposing_step_tol: float = 1e-3
    """A re-posing's solve is done once a full Newton step moves no unknown more than this (rad
    or m): the re-posing's own linearisation error is larger. The rest's solve (the last) goes
    to `tol`."""
    max_rotation_rad: float = 0.25
    """Largest joint rotation per re-posing (the linearisation's trust region)."""
    max_shift_m: float = 0.05
    settled_rotation_rad: float = 5e-3
    """Re-posing stops once no joint turns more than this (5 mrad: 1.5 mm at a forearm's end)."""
    settled_shift_m: float = 3e-4
    tissue_by_part: tuple[tuple[str, float], ...] = (("spine1", 0.15), ("spine2", 0.15))
    """Factors on the tissue modulus per J24 part: the belly and flanks (spine1-2 parts), soft
    tissue with no bone beneath, are softer than the rest."""
    tissue_depth: bool = True
    """Tissue modulus inversely proportional to the local tissue depth over the bone (the
    modulus `MattressParams.tissue_pa_per_m` is that of a TISSUE_REFERENCE_DEPTH_M layer):
    stiff over bony prominences, soft over muscle and fat. False: uniform tissue."""
    tissue_depth_max: tuple[tuple[str, float], ...] = (("spine2", 0.05), ("spine3", 0.05))
    """Largest tissue depth (m) per J24 part: the ribs lie under at most this much muscle and fat
    all around the chest, however far the point is from the spine's axis (the depth's bone);
    without it a side-lying chest sank into 15 cm of soft "tissue" and the head carried the
    shoulder's load (docs/realism.md "The ribcage")."""
    tissue_sag_m: float = 0.0
    """How far soft tissue 10 cm deep over its bone hangs toward the bed under its own weight (m;
    deeper tissue sags with the depth squared, `articulation.tissue_sag`): a side-lying waist or a
    supine buttock reaches the sheet where the bone alone would hold it off. 0: no sag."""
    sag_depth_max: tuple[tuple[str, float], ...] = (
        ("head", 0.005),
        ("spine2", 0.05),
        ("spine3", 0.05),
        ("left_hand", 0.01),
        ("right_hand", 0.01),
        ("left_foot", 0.01),
        ("right_foot", 0.01),
    )
    """Largest depth (m) per J24 part for the sag: the skull, the ribcage, the hands' and feet's
    bones lie that close under the skin (the leaf parts' depth is measured to their centroid)."""
    hold_roll_m: float = 0.0
    """Trunk roll hold: a spring on the body's roll about the bed's long axis of this many metres
    x its weight per radian (0: none; side-lying bodies need ~0.5 to stay on their side, as in
    sim #1's `lateral_straight`)."""
    sub: int = 2
    """Grid cells per taxel side."""
    coarse_sub: int = 1
    """The re-posings before the last `fine_reposings` find their contacts on a coarse grid of
    this many cells per taxel side with the mesh's vertices only (a third of the surface
    points); the last ones and the rest itself on the image's grid (`sub`) with every point.
    0: the image's grid throughout (with `outer` 20: engine revision 8)."""
    fine_reposings: int = 8
    """Re-posings on the image's grid at least (all of them if `outer` is not larger)."""
    coarse_inner: int = 3
    """Newton steps of a coarse re-posing's solve (`inner_reposing` on the image's grid): it
    only brings the body nearer its rest (6: 7-10% more CPU, more bodies still moving at the cap;
    docs/benchmarks.md "Session 49: two grids")."""
    self_contact: bool = True
    """Keep the body's capsules from passing through each other (`sim.self_contact`): a
    forearm across the belly rests on it instead of sinking through to the foam."""
    self_contact_sink_m: float = 0.05
    """Self-contact stiffness: the body's whole weight on one contact would press it this far in
    (5 cm since session 42, 2 cm before: soft tissue between a resting arm and the trunk, or
    between the knees of a side-lying body; docs/realism.md)."""
    friction: bool = True
    """Static friction per part (`sim.friction`, MattressParams.friction): a part that touched
    the sheet sticks there until pushed beyond mu x its load."""
    pillow: Pillow = Pillow()
    """The pillow under the heads of the bodies given one (`rest_articulated(pillow_m=...)`,
    `sim.pillow`): its size and material."""
    wedge: Wedge | None = None
    """A wedge under the back of every body that starts turned 5-90 deg from supine, sloped at
    its turn (`sim.wedge`; the `tilted` partition's); None: no wedges."""
    tol: float = 1e-4
    """Converged when the force imbalance is below tol x the weight and the steps are tiny."""

    @property
    def coarse_reposings(self) -> int:
        """How many re-posings every body takes on the coarse grid (0: none, `coarse_sub` 0 or
        `fine_reposings` >= `outer`)."""
        return max(self.outer - self.fine_reposings, 0) if self.coarse_sub else 0

    def __post_init__(self) -> None:
        if not (0 <= self.coarse_sub < self.sub) or self.fine_reposings < 1 or self.coarse_inner < 1:
            raise UserError(
                f"ArticulatedConfig: coarse_sub ({self.coarse_sub}) must be 0 (no coarse grid) or below sub"
                f" ({self.sub}), fine_reposings ({self.fine_reposings}) and coarse_inner ({self.coarse_inner}) >= 1"
            )
        if not self.tissue_sag_m >= 0:  # also refuses NaN
            raise UserError(f"ArticulatedConfig.tissue_sag_m must be >= 0 m (0: no sag), got {self.tissue_sag_m}")
        for field in ("tissue_by_part", "tissue_depth_max", "sag_depth_max", "lying_extension"):
            for entry in getattr(self, field):
                if not (
                    isinstance(entry, tuple | list)
                    and len(entry) == 2
                    and isinstance(entry[0], str)
                    and isinstance(entry[1], int | float)
                ):
                    raise UserError(
                        f"ArticulatedConfig.{field}: each entry is a (J24 part, number) pair, got {entry!r}"
                    )
                name = entry[0]
                if name not in J24_NAMES:
                    raise UserError(
                        f"ArticulatedConfig.{field}: unknown part {name!r}; parts are J24's: {', '.join(J24_NAMES)}"
                    )
        for name, rad in self.lying_extension:
            if name == "pelvis" or not math.isfinite(rad):
                raise UserError(
                    f"ArticulatedConfig.lying_extension: ({name!r}, {rad}) must name a joint below the pelvis (the"
                    " root has no spring) with a finite angle in rad"
                )


__all__ = ["ArticulatedConfig"]
