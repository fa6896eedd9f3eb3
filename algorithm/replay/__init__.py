"""Replay: the table interface, the prioritized in-process table, its sum tree and rate limiter."""

from algorithm.replay.base import NormalizerStats, ReplayInfo, ReplayTable, ReplayUnavailable, SampleTimeout
from algorithm.replay.dedup import ChunkIds, Inserted, ProducerLimitReached
from algorithm.replay.rate_limiter import InsertTimeout, RateLimiter
from algorithm.replay.sum_tree import SumTree
from algorithm.replay.table import PrioritizedTable

__all__ = [
    "ChunkIds",
    "Inserted",
    "InsertTimeout",
    "NormalizerStats",
    "PrioritizedTable",
    "ProducerLimitReached",
    "RateLimiter",
    "ReplayInfo",
    "ReplayTable",
    "ReplayUnavailable",
    "SampleTimeout",
    "SumTree",
]
