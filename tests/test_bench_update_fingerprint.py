"""bench/update_fingerprint.py, the check that a restructuring leaves every feature's update as it was,
can tell: the same code prints the same fingerprint, and any change to an update prints another."""

from __future__ import annotations

from typing import Any

import pytest

from algorithm.sac import features, losses
from bench.update_fingerprint import fingerprint


@pytest.mark.parametrize("name", ["recurrent", "update options"])
def test_the_same_run_gives_the_same_fingerprint_and_another_update_another(
    name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    first = fingerprint(name)
    assert fingerprint(name) == first
    assert fingerprint(name, ["sac.learning_rate=0.0007"]) != first

    original = losses.critic_loss

    def a_hair_larger(*args: Any, **kwargs: Any) -> Any:  # the same critic loss, scaled by 1 + 1e-6
        loss, td_abs, metrics = original(*args, **kwargs)
        return loss * (1 + 1e-6), td_abs, metrics

    for module in (losses, features):  # the plain critic's loss, and the clipped critic's (update options clip)
        monkeypatch.setattr(module, "critic_loss", a_hair_larger)
    assert fingerprint(name) != first
