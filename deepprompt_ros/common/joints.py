"""How joint lists are written in messages to users (one rule for the whole package)."""
from __future__ import annotations

from typing import Sequence

__all__ = ["joint_list_text"]


def joint_list_text(names: Sequence[str]) -> str:
    """``"joint_1..joint_6"`` for three or more consecutively numbered names with one stem, else
    the names separated by commas (``"wam_j1, elbow, wrist"``)."""
    names = [str(n) for n in names]
    if len(names) >= 3:
        stem = names[0].rstrip("0123456789")
        tails = [n[len(stem):] for n in names]
        if all(n.startswith(stem) for n in names) and all(t.isdigit() for t in tails):
            nums = [int(t) for t in tails]
            if nums == list(range(nums[0], nums[0] + len(nums))):
                return f"{names[0]}..{names[-1]}"
    return ", ".join(names)
