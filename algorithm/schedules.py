"""Values that move with the learner's applied-update count (``SAC.updates``, which checkpoints keep,
so a resumed run goes on where it was)."""

from __future__ import annotations


def linear_anneal(start: float, final: float, updates: int, over: int) -> float:
    """``start`` moved linearly to ``final`` over ``over`` updates, ``final`` after."""
    done = min(1.0, updates / over)
    return start + (final - start) * done
