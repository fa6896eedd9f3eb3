"""ds/net/grpc_env.py: role processes read gRPC replies on the calling thread unless the user chose."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def _python(code: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)


def _without_experiments() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k != "GRPC_EXPERIMENTS"}


def test_a_role_process_turns_the_event_engine_client_off_and_children_inherit_it() -> None:
    code = (
        "from ds.net.grpc_env import read_replies_on_calling_thread\n"
        "read_replies_on_calling_thread()\n"
        "import grpc, os, subprocess, sys\n"
        "print(os.environ['GRPC_EXPERIMENTS'])\n"
        "print(subprocess.run([sys.executable, '-c', 'import os; print(os.environ[\"GRPC_EXPERIMENTS\"])'],"
        " capture_output=True, text=True).stdout.strip())\n"
    )
    done = _python(code, _without_experiments())
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["-event_engine_client", "-event_engine_client"]


def test_the_users_own_setting_wins() -> None:
    code = "from ds.net.grpc_env import read_replies_on_calling_thread\nread_replies_on_calling_thread()\n"
    code += "import os; print(os.environ['GRPC_EXPERIMENTS'])"
    done = _python(code, {**_without_experiments(), "GRPC_EXPERIMENTS": "event_engine_client"})
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "event_engine_client"


def test_called_after_grpc_is_imported_it_says_so_instead_of_doing_nothing() -> None:
    code = "import grpc\nfrom ds.net.grpc_env import read_replies_on_calling_thread\nread_replies_on_calling_thread()"
    done = _python(code, _without_experiments())
    assert done.returncode != 0
    assert "must run before grpc is imported" in done.stderr


def test_main_ds_sets_it_before_grpc_is_imported() -> None:
    """The role entry point: grpc not yet imported where it is called, and the variable set once
    main_ds.py has started (its --help exits before any role runs)."""
    code = (
        "import runpy, sys\n"
        "sys.argv = ['main_ds.py', '--help']\n"
        "try:\n"
        "    runpy.run_path('main_ds.py', run_name='__main__')\n"
        "except SystemExit:\n"
        "    pass\n"
        "import os; print('GRPC', os.environ.get('GRPC_EXPERIMENTS'))\n"
    )
    done = _python(code, _without_experiments())
    assert done.returncode == 0, done.stderr
    assert "GRPC -event_engine_client" in done.stdout
