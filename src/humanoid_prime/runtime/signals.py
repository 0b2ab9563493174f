"""Stop on SIGINT, SIGTERM and SIGHUP with an orderly teardown."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


@contextlib.contextmanager
def stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP set ``stop``: the loop ends and everything is torn down in order (gate
    reset, drives disabled, wrists off). Later signals are ignored, so a second Ctrl-C cannot cut the
    teardown in half; every step of it is bounded by its own timeout. Enter this before the ExitStack that
    holds the session, so the handlers stay in place until the teardown is over."""
    previous = {}

    def handler(signum: int, frame: object) -> None:
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        previous[sig] = signal.signal(sig, handler)
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
