"""The run lifecycle of one process: the acting loop both modes use (actor.py), the learner's
lifecycle written once (learner_core.py) and the single-process trainer built on both (trainer.py),
the run's counters and summary (progress.py), its folder and the lock on it (folder.py,
folder_lock.py), checkpoints (checkpoint.py), evaluation (evaluation.py), logs and metrics
(logging.py) and stopping on a signal (signals.py). Atomic writes are algorithm/files.py, which the
replay's snapshots use too."""
