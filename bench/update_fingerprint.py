"""A fingerprint of what each algorithm feature's update computes, for restructurings that must not
change it (issue: plain SAC on one page; "updates stay bit-identical").

    python -m bench.update_fingerprint [--out FILE] [--only NAME ...]     # one line per entry
    diff BEFORE AFTER                                                    # nothing: nothing changed

Each entry of the feature matrix (tests/test_features.py ``ENTRIES``: every row of docs/features.md
and the combinations) trains its short run (``SMALL``, seed 0) in this process, as ``main.py`` does,
on one torch thread. The fingerprint is a SHA-256 over every update's ``td_abs`` and metrics (the
metrics when the run asked for them) and the final ``SAC.state_dict()`` (weights, targets,
optimizers, alpha, counters, RNG states), so two runs of the same code print the same line
(tests/test_bench_update_fingerprint.py) and a change anywhere in an update prints another.
"""

from __future__ import annotations

import argparse
import hashlib
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from algorithm.config.load import load_config
from algorithm.run.trainer import EmbeddedTrainer
from algorithm.sac.learner import SAC, UpdateResult
from cli import copy_model_file, env_factory, task_dir
from tests.test_features import ENTRIES, SMALL


def _feed(digest: Any, value: Any) -> None:
    """Hash ``value``: tensors and arrays by dtype, shape and bytes; containers in a fixed order."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu()
        digest.update(f"{value.dtype}{tuple(value.shape)}".encode())
        digest.update(value.reshape(-1).contiguous().view(torch.uint8).numpy().tobytes() if value.numel() else b"")
    elif isinstance(value, np.ndarray):
        digest.update(f"{value.dtype}{value.shape}".encode())
        digest.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, dict):
        for key in sorted(value, key=str):
            digest.update(str(key).encode())
            _feed(digest, value[key])
    elif isinstance(value, list | tuple):
        for item in value:
            _feed(digest, item)
    elif isinstance(value, float):
        digest.update(value.hex().encode())
    else:
        digest.update(repr(value).encode())


def fingerprint(name: str, extra: list[str] = ()) -> str:  # type: ignore[assignment]
    """The fingerprint of entry ``name``'s short run (``extra``: more overrides, for the tests)."""
    task, section, switches = ENTRIES[name]
    overrides = [s for s in switches if not s.startswith("--")] + SMALL + ["sac.seed=0", *extra]
    nn = [s.split("=", 1)[1] for s in switches if s.startswith("--nn=")]
    if nn:
        overrides.append(f"base_config.nn={nn[0]}")
    folder = task_dir(task)
    config = load_config(folder, section, overrides).config
    digest = hashlib.sha256()
    original = SAC.update

    def recorded(self: SAC, batch: Any, with_metrics: bool = False) -> UpdateResult:
        result = original(self, batch, with_metrics)
        _feed(digest, [result.td_abs, result.metrics, result.skipped, result.refreshed_rnn_states])
        return result

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        copy_model_file(folder, config, run_dir, explicit=bool(nn))
        SAC.update = recorded  # type: ignore[method-assign]
        try:
            trainer = EmbeddedTrainer(config, run_dir, env_factory(config), progress=False)
            summary = trainer.run()
        finally:
            SAC.update = original  # type: ignore[method-assign]
        _feed(digest, [summary.env_steps, summary.updates, trainer.sac.state_dict()])
    return digest.hexdigest()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="also write the lines to this file")
    parser.add_argument("--only", nargs="*", default=None, help="entry names (default: all)")
    args = parser.parse_args()
    lines = []
    for name in args.only or list(ENTRIES):
        lines.append(f"{fingerprint(name)}  {name}")
        print(lines[-1], flush=True)
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
