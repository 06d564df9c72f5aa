"""J24: the 24-joint tree of SMPL, in SMPL's order, shared by every body backend."""

from __future__ import annotations

J24_NAMES: tuple[str, ...] = (
    "pelvis",  # 0 (root)
    "left_hip",  # 1
    "right_hip",  # 2
    "spine1",  # 3
    "left_knee",  # 4
    "right_knee",  # 5
    "spine2",  # 6
    "left_ankle",  # 7
    "right_ankle",  # 8
    "spine3",  # 9
    "left_foot",  # 10
    "right_foot",  # 11
    "neck",  # 12
    "left_collar",  # 13
    "right_collar",  # 14
    "head",  # 15
    "left_shoulder",  # 16
    "right_shoulder",  # 17
    "left_elbow",  # 18
    "right_elbow",  # 19
    "left_wrist",  # 20
    "right_wrist",  # 21
    "left_hand",  # 22
    "right_hand",  # 23
)

# Parent of each joint (-1 for the root), SMPL's kinematic tree.
J24_PARENTS: tuple[int, ...] = (
    -1,
    0,
    0,
    0,
    1,
    2,
    3,
    4,
    5,
    6,
    7,
    8,
    9,
    9,
    9,
    12,
    13,
    14,
    16,
    17,
    18,
    19,
    20,
    21,
)

NUM_JOINTS = 24
NUM_POSE_JOINTS = 23  # every joint but the root carries a local rotation in the pose vector


def joint_index(name: str) -> int:
    """Index of a J24 joint by name; ValueError naming the valid names otherwise."""
    try:
        return J24_NAMES.index(name)
    except ValueError:
        raise ValueError(f"unknown joint name {name!r}; expected one of {', '.join(J24_NAMES)}") from None


def _mirror_name(name: str) -> str:
    if name.startswith("left_"):
        return "right_" + name[5:]
    if name.startswith("right_"):
        return "left_" + name[6:]
    return name


# The joints by body region, as the error reports group them (`eval.evaluation`).
J24_REGIONS: dict[str, tuple[str, ...]] = {
    "head": ("neck", "head"),
    "torso": ("pelvis", "spine1", "spine2", "spine3", "left_collar", "right_collar"),
    "arms": tuple(f"{s}_{n}" for s in ("left", "right") for n in ("shoulder", "elbow", "wrist", "hand")),
    "legs": tuple(f"{s}_{n}" for s in ("left", "right") for n in ("hip", "knee", "ankle", "foot")),
}
# The head and torso joints by index: every simulated image pins them (their heatmap spreads say
# how sure a network is where a body lies, docs/network.md "How far to trust a joint").
TRUNK_JOINTS: tuple[int, ...] = tuple(J24_NAMES.index(n) for n in (*J24_REGIONS["head"], *J24_REGIONS["torso"]))

# Index of each joint's left/right counterpart (itself on the midline).
J24_MIRROR: tuple[int, ...] = tuple(J24_NAMES.index(_mirror_name(n)) for n in J24_NAMES)


def mirror_joints(joints, width_m: float):
    """J24 positions (..., 24, D >= 2; mat frame, y across the bed) of the body mirrored across
    the mat's centre line: y -> width_m - y, left and right joints swapped (J24_MIRROR). The
    training's mirror augmentation and the flip test map joints with it."""
    out = joints[..., list(J24_MIRROR), :].clone()
    out[..., 1] = width_m - out[..., 1]
    return out
