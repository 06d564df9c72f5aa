"""The part of Anny's skeleton a pass needs (`body.anny_backend`): its bones in a level order
for batched forward kinematics (`order`, `level_sizes`: the root, then each depth's bones; each
bone's parent as a position in the level above), their parents and labels."""

from __future__ import annotations

import torch

from pressurepose.body.joints import J24_NAMES


class Skeleton(torch.nn.Module):
    """A subset of Anny's bones closed under ancestors, with local parent indices and the
    depth levels the forward kinematics walks through."""

    def __init__(self, bones: list[int], all_parents: list[int], labels: list[str]) -> None:
        super().__init__()
        local = {b: i for i, b in enumerate(bones)}
        parents = [0] + [local[all_parents[b]] for b in bones[1:]]
        depth = [0] * len(bones)
        for i in range(1, len(bones)):
            depth[i] = depth[parents[i]] + 1
        order = [0]
        levels = []
        for d in range(1, max(depth) + 1):
            level = [i for i in range(len(bones)) if depth[i] == d]
            levels.append(level)
            order += level
        position = {b: p for p, b in enumerate(order)}
        self.register_buffer("bones", torch.tensor(bones), persistent=False)
        self.register_buffer("order", torch.tensor(order), persistent=False)
        self.register_buffer("parents", torch.tensor(parents), persistent=False)
        self.register_buffer("inverse_order", torch.tensor([position[i] for i in range(len(bones))]), persistent=False)
        for d, level in enumerate(levels):
            above = [0] if d == 0 else levels[d - 1]  # a bone's parent lies one level up
            self.register_buffer(
                f"level_parent{d}", torch.tensor([above.index(parents[i]) for i in level]), persistent=False
            )
        self.level_sizes = [1] + [len(level) for level in levels]
        j = {labels[b]: i for i, b in enumerate(bones)}  # bone name -> local index
        self.arms = []
        for s, sign in (("L", 1.0), ("R", -1.0)):
            fore_root = labels.index(f"lowerarm01.{s}")
            fore = [local[b] for b in bones if _descends(all_parents, b, fore_root)]
            self.arms.append(
                dict(
                    sign=sign,
                    elbow=j[f"lowerarm01.{s}"],
                    twist=j[f"lowerarm02.{s}"],
                    upper=[j[f"upperarm01.{s}"], j[f"upperarm02.{s}"]],
                    fore=fore,
                    upper_chain=[j[f"upperarm02.{s}"], j[f"lowerarm01.{s}"]],
                    fore_chain=[j[f"lowerarm02.{s}"], j[f"wrist.{s}"]],
                    elbow_joint=J24_NAMES.index("left_elbow" if s == "L" else "right_elbow"),
                )
            )

        # per bone, where its T-pose correction comes from (`AnnyBody._t_pose_corrections`):
        # 0 the identity, 1 + i arm i's upper-arm rotation, 1 + len(arms) + i its forearm's
        source = [0] * len(bones)
        for i, arm in enumerate(self.arms):
            for b in arm["upper"]:
                source[b] = 1 + i
            for b in arm["fore"]:
                source[b] = 1 + len(self.arms) + i
        self.register_buffer("correction_source", torch.tensor(source), persistent=False)

    @property
    def level_parents(self) -> list[torch.Tensor]:
        """Per level below the root, each bone's parent as a position in the level above."""
        return [getattr(self, f"level_parent{d}") for d in range(len(self.level_sizes) - 1)]


def _descends(parents: list[int], bone: int, ancestor: int) -> bool:
    while bone > 0 and bone != ancestor:
        bone = parents[bone]
    return bone == ancestor


__all__ = ["Skeleton"]
