"""Rows leaving a lockstep batch: the step both lockstep runners share (stage 2's,
:mod:`services.learner.feedback_lockstep`, and PPO's, :mod:`services.learner.ppo.lockstep`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar

ItemT = TypeVar("ItemT")
ResultT = TypeVar("ResultT")


class BatchedRows(Protocol):
    """A batched model or optimizer: a leading run dimension that can be cut to rows."""

    def keep(self, rows: list[int]) -> None: ...


def leave_batch(
    items: list[ItemT],
    slots: list[int],
    keep: list[int],
    failed: dict[int, Exception],
    outcomes: list[ResultT | Exception | None],
    finish: Callable[[ItemT], ResultT],
    batched: Sequence[BatchedRows],
) -> tuple[list[ItemT], list[int]]:
    """Settle every row not in ``keep`` into ``outcomes`` (at its slot): what it raised
    (``failed``), else its ``finish`` (or what that raised); cut the ``batched`` tensors to
    the kept rows. Returns the kept items and their slots."""
    for row, item in enumerate(items):
        if row in keep:
            continue
        if row in failed:
            outcomes[slots[row]] = failed[row]
            continue
        try:
            outcomes[slots[row]] = finish(item)
        except Exception as exc:
            outcomes[slots[row]] = exc
    if len(keep) < len(items):
        for tensors in batched:
            tensors.keep(keep)
    return [items[r] for r in keep], [slots[r] for r in keep]
