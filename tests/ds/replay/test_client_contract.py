"""The replay contract tests of tests/algorithm/replay, unchanged, against the gRPC client.

Each test below is the in-process test itself, imported and collected again here with ``connect``
overridden: the test builds its table as before, and ``connect`` starts a real server for it on
127.0.0.1 and hands back a :class:`~ds.replay.client.ReplayClient`, through which the test then
does everything (docs/architecture.md section 13). Not listed, because they reach inside the table or test its
constructor rather than its interface: ``test_constructor_rejects_bad_arguments``, the
thread-safety test of test_table_threads.py (its gRPC counterpart is in test_service.py)
and the tests of the dedup ledger's bounds.
"""

from __future__ import annotations

import pytest

from tests.algorithm.replay.conftest import Connect
from tests.algorithm.replay.test_table import (  # noqa: F401  (collected by pytest)
    test_a_table_without_rnn_state_refuses_rnn_state_updates,
    test_all_zero_priorities_sample_uniformly_among_step_rows,
    test_alpha_zero_is_uniform_whatever_the_priorities,
    test_bad_chunks_are_named_and_store_nothing,
    test_bad_priority_updates_are_named,
    test_bad_rnn_state_updates_are_named_and_change_nothing,
    test_chunk_longer_than_capacity_is_refused,
    test_fifo_eviction_and_stale_updates_are_ignored,
    test_from_config_wires_the_rate_limiter,
    test_images_stay_uint8_and_rnn_state_comes_from_the_window_start,
    test_insert_many_is_admitted_as_one_request,
    test_insert_many_stores_all_chunks_or_none,
    test_keys_are_consecutive_per_chunk_and_skip_bootstrap_rows,
    test_new_rows_get_the_highest_priority_seen,
    test_normalizer_sees_every_inserted_observation_of_vector_sensors,
    test_refreshed_rnn_states_replace_the_stored_ones_of_live_keys_only,
    test_sample_times_out_below_min_size,
    test_sampled_frequencies_follow_transformed_priorities,
    test_zero_priority_rows_are_never_drawn,
)
from tests.algorithm.replay.test_table_burn_in import (  # noqa: F401
    test_look_back_windows_never_leave_the_sampled_chunk,
    test_the_sampled_step_sits_after_the_burn_in_and_early_steps_get_zero_rows,
)
from tests.algorithm.replay.test_table_dedup import (  # noqa: F401
    test_a_chunk_sent_again_is_answered_with_its_keys_and_stored_once,
    test_a_new_producer_forgotten_while_it_waits_in_the_rate_limiter_comes_back_in,
    test_a_request_of_duplicates_only_is_not_held_back_by_the_rate_limiter,
    test_a_snapshot_with_a_bad_ledger_is_refused,
    test_a_stopping_producers_last_tries_are_stored_past_the_rate_limiter_once,
    test_a_table_loaded_from_a_snapshot_knows_the_chunks_the_snapshot_holds,
    test_acknowledged_numbers_are_forgotten_and_a_stale_copy_is_not_stored,
    test_bad_ids_are_named_and_store_nothing,
    test_copies_waiting_in_the_rate_limiter_store_the_chunk_once,
    test_past_max_producers_a_new_producer_is_refused_and_no_chunk_is_stored_twice,
)
from tests.algorithm.replay.test_table_persistence import (  # noqa: F401
    test_bad_file_raises_and_leaves_the_table_intact,
    test_mismatched_table_is_refused,
    test_round_trip_continues_sampling_identically,
    test_save_overwrites_atomically,
)
from tests.algorithm.replay.test_table_windows import (  # noqa: F401
    test_window_past_the_chunk_end_is_masked_and_repeats_the_final_observation,
    test_windows_after_a_key_are_the_oldest_stored_steps_from_it_in_key_order,
    test_windows_never_span_two_chunks,
)
from tests.ds.conftest import ServeOverGrpc

pytestmark = pytest.mark.grpc


@pytest.fixture
def connect(over_grpc: ServeOverGrpc) -> Connect:
    return over_grpc
