"""Values that move with the learner's applied-update count (``SAC.updates``, which checkpoints keep,
so a resumed run goes on where it was)."""

from __future__ import annotations

from algorithm.config.schema import SacConfig


def linear_anneal(start: float, final: float, updates: int, over: int) -> float:
    """``start`` moved linearly to ``final`` over ``over`` updates, ``final`` after."""
    done = min(1.0, updates / over)
    return start + (final - start) * done


def discrete_target_entropy_ratio(sac: SacConfig, updates: int) -> float:
    """The discrete target entropy as a fraction of log|A_b| after ``updates`` updates: constant,
    or with ``discrete_target_entropy_start`` moving linearly from it to the final ratio. A
    high target early keeps both actions in use where a young critic's spurious action gaps
    would otherwise make the policy deterministic before they are corrected; the final, lower
    target lets it exploit. The idea is TES-SAC's (Xu et al. 2021, arXiv:2112.02852), which
    lowers the target in steps as the policy's entropy settles; this schedule is linear."""
    final, start = sac.discrete_target_entropy_ratio, sac.discrete_target_entropy_start
    if start is None:
        return final
    return linear_anneal(start, final, updates, sac.discrete_target_entropy_anneal_updates)


def munchausen_scale_at(sac: SacConfig, updates: int) -> float:
    """The Munchausen term's weight after ``updates`` updates: ``munchausen_scale``, or with
    ``munchausen_scale_start`` set, moving linearly from it to ``munchausen_scale`` on the step size's
    schedule (``learning_rate_anneal_updates``). Starting at 0 keeps the early learning of plain targets,
    which the term slows, and gives the later updates its wider action gaps (bench/results/cartpole/README.md)."""
    start, final = sac.munchausen_scale_start, sac.munchausen_scale
    if start is None:
        return final
    return linear_anneal(start, final, updates, _anneal_updates(sac))


def learning_rate_at(sac: SacConfig, updates: int) -> float:
    """The step size of the update after ``updates`` applied ones: ``learning_rate``, or with
    ``learning_rate_final`` set, moving linearly from it to that value over
    ``learning_rate_anneal_updates`` updates and constant after (as SB3's linear schedules,
    with any end). It follows the applied-update count, which checkpoints keep."""
    start, final = sac.learning_rate, sac.learning_rate_final
    if final is None:
        return start
    return linear_anneal(start, final, updates, _anneal_updates(sac))


def _anneal_updates(sac: SacConfig) -> int:
    if sac.learning_rate_anneal_updates is None:  # a whole Config fills it in from the run's length
        raise ValueError("sac_config.learning_rate_anneal_updates is null outside a whole config: give it a number")
    return sac.learning_rate_anneal_updates
