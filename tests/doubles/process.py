"""Child processes started as a command typed in a terminal would be."""

from __future__ import annotations

import signal
import subprocess
from typing import Any


def terminal_signals() -> None:
    """``preexec_fn``: SIGINT takes its default action in the child, whatever the test runner inherited. A
    runner started in the background by a non-interactive shell ignores SIGINT, and so would every child
    it starts, which would hide what a Ctrl-C does."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def popen(*args: Any, **kwargs: Any) -> subprocess.Popen:
    """``subprocess.Popen`` with ``terminal_signals`` in the child."""
    return subprocess.Popen(*args, preexec_fn=terminal_signals, **kwargs)


def stop(process: subprocess.Popen, timeout: float = 60.0) -> None:
    """End a running prime command as Ctrl-C does (its teardown runs), then wait; kill it only if it hangs."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    try:
        process.wait(timeout=timeout)
    finally:
        if process.poll() is None:
            process.kill()
