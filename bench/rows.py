"""Result rows of the bench commands: one CSV file per command, one row per run, appended as each run
ends so that a stopped command keeps what it measured.

    append_row(Path("bench/results/tasks.csv"), FIELDS, {"task": "gym/cartpole", ...})
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path


def append_row(path: Path, fields: Sequence[str], row: Mapping[str, object]) -> None:
    """Append ``row`` (keys ``fields``) to ``path``, writing the header first in a new file. A file
    written before a column was added is rewritten with the new header first: its rows keep their
    values, the new column left empty."""
    path.parent.mkdir(parents=True, exist_ok=True)
    old: list[dict[str, str]] = []
    rewrite = not path.exists()
    if not rewrite:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            rewrite = reader.fieldnames != list(fields)
            old = list(reader) if rewrite else []
    if rewrite:
        with path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fields)
            writer.writeheader()
            writer.writerows({k: r.get(k, "") for k in fields} for r in old)
    with path.open("a", newline="") as f:
        csv.DictWriter(f, fields).writerow(row)
