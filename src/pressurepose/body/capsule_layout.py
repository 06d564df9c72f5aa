"""The capsule layout on J24 (SMPLify's, seed A.1), collision pairs, the mass and stiffness
tables (REFERENCE.md, Tozeren; seed A.2) and the home pose; `body.capsules` has the whole story."""

from __future__ import annotations

import dataclasses
import math

import torch

from pressurepose.body.joints import J24_NAMES, J24_PARENTS, NUM_POSE_JOINTS

_J = J24_NAMES.index


@dataclasses.dataclass(frozen=True)
class CapsuleSpec:
    name: str
    joint: int  # J24 joint the capsule rides on
    child: int | None  # axis end joint (None: crosswise torso capsule)
    parts: tuple[int, ...]  # J24 parts whose vertices fit the capsule
    segment: str  # body segment for the mass distribution
    extend_end: bool = False  # grow the far end to the last vertex (head, hands, feet)
    extend_start: bool = False  # grow the near end back to the first vertex (heels)

    @property
    def crosswise(self) -> bool:
        """Torso capsules lie across the body (SMPLify); the head has no child but an axis."""
        return self.child is None and self.name != "head"


def _layout() -> tuple[CapsuleSpec, ...]:
    specs = [
        CapsuleSpec("pelvis", _J("pelvis"), None, (_J("pelvis"),), "trunk"),
        CapsuleSpec("spine1", _J("spine1"), None, (_J("spine1"),), "trunk"),
        CapsuleSpec("spine2", _J("spine2"), None, (_J("spine2"),), "trunk"),
        CapsuleSpec("spine3", _J("spine3"), None, (_J("spine3"),), "trunk"),
        CapsuleSpec("neck", _J("neck"), _J("head"), (_J("neck"),), "head"),
        CapsuleSpec("head", _J("head"), None, (_J("head"),), "head", extend_end=True),
    ]
    for s in ("left", "right"):
        specs += [
            CapsuleSpec(f"{s}_collar", _J(f"{s}_collar"), _J(f"{s}_shoulder"), (_J(f"{s}_collar"),), "trunk"),
            CapsuleSpec(f"{s}_upper_arm", _J(f"{s}_shoulder"), _J(f"{s}_elbow"), (_J(f"{s}_shoulder"),), "upper_arm"),
            CapsuleSpec(f"{s}_forearm", _J(f"{s}_elbow"), _J(f"{s}_wrist"), (_J(f"{s}_elbow"),), "forearm"),
            CapsuleSpec(
                f"{s}_hand",
                _J(f"{s}_wrist"),
                _J(f"{s}_hand"),
                (_J(f"{s}_wrist"), _J(f"{s}_hand")),
                "hand",
                extend_end=True,
            ),
            CapsuleSpec(f"{s}_thigh", _J(f"{s}_hip"), _J(f"{s}_knee"), (_J(f"{s}_hip"),), "thigh"),
            CapsuleSpec(f"{s}_calf", _J(f"{s}_knee"), _J(f"{s}_ankle"), (_J(f"{s}_knee"),), "shank"),
            CapsuleSpec(
                f"{s}_foot",
                _J(f"{s}_ankle"),
                _J(f"{s}_foot"),
                (_J(f"{s}_ankle"), _J(f"{s}_foot")),
                "foot",
                extend_end=True,
                extend_start=True,
            ),
        ]
    return tuple(specs)


CAPSULES: tuple[CapsuleSpec, ...] = _layout()
CAPSULE_NAMES: tuple[str, ...] = tuple(c.name for c in CAPSULES)
NUM_CAPSULES = len(CAPSULES)  # 20
CAPSULE_JOINTS: tuple[int, ...] = tuple(c.joint for c in CAPSULES)


def capsule_index(name: str) -> int:
    if name not in CAPSULE_NAMES:
        raise ValueError(f"unknown capsule {name!r}; expected one of {', '.join(CAPSULE_NAMES)}")
    return CAPSULE_NAMES.index(name)


def _capsule_parents() -> tuple[int, ...]:
    """Parent capsule of each capsule (-1 for the pelvis): the capsule riding the nearest
    J24 ancestor that has one."""
    by_joint = {c.joint: i for i, c in enumerate(CAPSULES)}
    out = []
    for c in CAPSULES:
        j = J24_PARENTS[c.joint]
        while j >= 0 and j not in by_joint:
            j = J24_PARENTS[j]
        out.append(by_joint.get(j, -1))
    return tuple(out)


CAPSULE_PARENTS: tuple[int, ...] = _capsule_parents()

# Seed A.1: hands, forearms, feet and lower legs are checked against every other capsule
# except their neighbours in the capsule tree (a forearm overlaps its upper arm by design).
DISTAL_CAPSULES: tuple[str, ...] = tuple(
    f"{s}_{p}" for s in ("left", "right") for p in ("hand", "forearm", "foot", "calf")
)


def collision_pairs(checked: tuple[str, ...] = DISTAL_CAPSULES) -> torch.Tensor:
    """(P, 2) capsule index pairs to test: each checked capsule against every non-adjacent
    capsule, each pair once."""
    pairs = set()
    for name in checked:
        a = capsule_index(name)
        for b in range(NUM_CAPSULES):
            if b == a or CAPSULE_PARENTS[a] == b or CAPSULE_PARENTS[b] == a:
                continue
            pairs.add((min(a, b), max(a, b)))
    return torch.tensor(sorted(pairs), dtype=torch.long).reshape(-1, 2)


# --- mass distribution (REFERENCE.md, Tozeren) ---------------------------------------------
AVERAGE_MASS_KG = {"female": 62.5, "male": 78.4}
SEGMENT_FRACTIONS = {  # per side for limbs
    "female": {
        "trunk": 0.508,
        "head": 0.094,
        "thigh": 0.083,
        "shank": 0.055,
        "foot": 0.012,
        "upper_arm": 0.027,
        "forearm": 0.016,
        "hand": 0.005,
    },
    "male": {
        "trunk": 0.483,
        "head": 0.071,
        "thigh": 0.105,
        "shank": 0.045,
        "foot": 0.015,
        "upper_arm": 0.033,
        "forearm": 0.019,
        "hand": 0.006,
    },
}
STIFFNESS_REFERENCE_MASS_KG = 70.45
DAMPING_RATIO = 15.0  # damping = 15 x stiffness (N m s / rad)
# Seed A.2 joint stiffness (N m / rad) of an average person. The seed's shoulder is one joint;
# J24 splits it 1/3 collar : 2/3 shoulder, so we use two springs in series, collar 12 and
# shoulder 6: together 4 N m/rad, and a load bends them 1 : 2 as the sampling split does.
JOINT_STIFFNESS = {
    "hip": 6.0,
    "knee": 3.0,
    "ankle": 6.0,
    "collar": 12.0,
    "shoulder": 6.0,
    "elbow": 2.0,
    "wrist": 4.0,
    "spine1": 200.0,
    "spine2": 200.0,
    "spine3": 200.0,
    "neck": 200.0,
    "head": 200.0,
}
# Joints of the capsule chain: every joint a capsule rides on, except the root.
CHAIN_JOINTS: tuple[int, ...] = tuple(j for j in CAPSULE_JOINTS if j != 0)
HINGE_JOINTS = {  # joint -> hinge axis in SMPL body axes (knees flex about x, elbows about y)
    _J("left_knee"): (1.0, 0.0, 0.0),
    _J("right_knee"): (1.0, 0.0, 0.0),
    _J("left_elbow"): (0.0, 1.0, 0.0),
    _J("right_elbow"): (0.0, 1.0, 0.0),
}


def home_pose(batch_size: int = 1, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    """(B, 23, 3) spring equilibrium: legs straight, arms down at the sides (seed A.2).

    Shoulders are bent 90 deg down about the body's front axis, split 1/3 collar, 2/3 shoulder
    (left arm: -z, right arm: +z)."""
    pose = torch.zeros(batch_size, NUM_POSE_JOINTS, 3, dtype=dtype, device=device)
    for side, sign in (("left", -1.0), ("right", 1.0)):
        pose[:, _J(f"{side}_collar") - 1, 2] = sign * math.pi / 6
        pose[:, _J(f"{side}_shoulder") - 1, 2] = sign * math.pi / 3
    return pose
