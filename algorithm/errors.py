"""Errors that end a command with one line (``error: ...``) instead of a traceback, in a module that
imports nothing: the entry points (main.py, main_ds.py) catch them without importing torch, so a
mistyped flag, task, config key or run folder is answered before the heavy imports run (a fraction
of a second rather than the ~3 s of CPU that importing torch takes on a laptop core)."""


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, damaged, or not one of ours (or not this run's: another
    task's models); the message names the file."""


class RoleError(RuntimeError):
    """A distributed role cannot start (e.g. its port is taken); the message says what to change."""
