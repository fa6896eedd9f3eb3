"""The ``connect`` fixture: how a replay test reaches the table it built.

Here it returns the table itself. tests/ds/replay/test_client_contract.py collects the interface-level
tests of this folder again with ``connect`` overridden to start a gRPC server around the table on
loopback and return a :class:`ds.replay.client.ReplayClient`, so that the network path passes the
same contract tests as the in-process one (docs/architecture.md section 13). A test that only uses the public table
interface (``insert``, ``insert_many``, ``sample``, ``update_priorities``, ``info``,
``normalizer_stats``, ``save``, ``load``, and the ``sensors``/``action_size`` attributes) on what
``connect`` returned can be listed there.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from algorithm.replay import PrioritizedTable

Connect = Callable[[PrioritizedTable], Any]


@pytest.fixture
def connect() -> Connect:
    return lambda table: table
