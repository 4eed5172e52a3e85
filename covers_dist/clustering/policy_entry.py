"""One policy of the bank: its buffer of initial observations and its bookkeeping."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from .buffer import ObservationBuffer

__all__ = ["PolicyEntry", "batch_group", "check_int"]


@dataclass
class PolicyEntry:
    """One policy of the bank and its bookkeeping."""

    policy_id: int
    buffer: ObservationBuffer
    created_at_episode: int
    created_at_assignment: int
    created_at_time: float
    episodes: list[int] = field(default_factory=list)
    assignments: int = 0
    group_counts: Counter = field(default_factory=Counter)
    episodes_reported: int = 0
    last_success: float | None = None
    last_return: float | None = None

    def summary(self) -> dict[str, Any]:
        """JSON-safe view of the entry."""
        return {
            "policy_id": self.policy_id,
            "created_at_episode": self.created_at_episode,
            "created_at_assignment": self.created_at_assignment,
            "created_at_time": self.created_at_time,
            "episodes_assigned": len(self.episodes),
            "assignments": self.assignments,
            "buffer_size": len(self.buffer),
            "buffer_capacity": self.buffer.capacity,
            "frames_seen": self.buffer.seen,
            "group_histogram": {str(g): c for g, c in sorted(self.group_counts.items())},
            "episodes_reported": self.episodes_reported,
            "last_success": self.last_success,
            "last_return": self.last_return,
        }


def batch_group(groups: Sequence[int]) -> int:
    """The group of a batch in ground-truth mode: the most frequent; ties go to the latest episode's."""
    counts = Counter(groups)
    top = max(counts.values())
    return next(g for g in reversed(groups) if counts[g] == top)


def check_int(name: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)
