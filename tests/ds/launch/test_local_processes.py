"""The ``local`` launcher's children and their output (ds/launch/local.py), on real processes."""

from __future__ import annotations

import os
import pty
import sys

from ds.launch.local import LocalProcesses

HANG_S = 60.0  # a hang guard only: the child below ends in well under a second when it is read


def test_a_child_writing_on_after_the_terminal_hung_up_still_exits() -> None:
    """The launcher's terminal goes away (its far end closed: every write to it fails with EIO, as
    when a terminal window or SSH session closes) while a role goes on printing. Its lines can no
    longer be shown, but they must still be read: before, the reader thread died on the first failed
    write and the role blocked on a full pipe (64 KiB), unable to log its stop or exit, so a stopped
    ``local`` run left its roles lingering until SIGKILL."""
    terminal, far_end = pty.openpty()
    shown: list[str] = []

    def to_terminal(text: str) -> None:
        os.write(far_end, text.encode())
        shown.append(text)

    children = LocalProcesses(stream=to_terminal)
    os.close(terminal)  # hung up from here on
    try:
        # 500 KB of lines: several pipe buffers' worth
        children.start("replay", [sys.executable, "-c", "for i in range(5000): print('x' * 99)"])
        assert children.wait_all(HANG_S), "the child blocked on its full pipe"
        assert children.children["replay"].returncode == 0
        assert shown == []  # every write failed: nothing was claimed as shown
    finally:
        children.kill_all()
        os.close(far_end)


def test_lines_reach_the_stream_with_the_childs_label() -> None:
    shown: list[str] = []
    children = LocalProcesses(stream=shown.append)
    children.start("actor-0", [sys.executable, "-c", "print('one'); print('two')"])
    assert children.wait_all(HANG_S)
    children.drain()
    assert shown == ["[actor-0] one\n", "[actor-0] two\n"]
