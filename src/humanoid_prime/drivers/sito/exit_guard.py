"""Every active SitoSystem's motors disabled at interpreter exit and on SIGINT/SIGTERM (``EXIT_GUARD``)."""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
import threading
import types
from collections.abc import Callable
from typing import Protocol


class Disables(Protocol):
    def disable_motors(self) -> None: ...  # never raises; safe from any thread


# what signal.getsignal returns
_Handler = Callable[[int, types.FrameType | None], object] | int | None


class ExitGuard:
    """Disables every active system's motors at interpreter exit and on SIGINT/SIGTERM.

    A signal handler sends from a helper thread so it can never deadlock on a lock the interrupted
    main thread holds; then the previous handler runs as it would have.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self._systems: set[Disables] = set()  # strong: an active system must outlive its last user
        self._previous: dict[int, _Handler] = {}
        self._lock = threading.Lock()
        atexit.register(self.disable_all)

    def add(self, system: Disables) -> None:
        with self._lock:
            self._systems.add(system)
            if threading.current_thread() is threading.main_thread() and not self._previous:
                for signum in self.SIGNALS:
                    self._previous[signum] = signal.getsignal(signum)
                    signal.signal(signum, self._on_signal)

    def remove(self, system: Disables) -> None:
        with self._lock:
            self._systems.discard(system)
            if not self._systems and self._previous and threading.current_thread() is threading.main_thread():
                for signum, previous in self._previous.items():
                    if signal.getsignal(signum) == self._on_signal:
                        signal.signal(signum, previous if previous is not None else signal.SIG_DFL)
                self._previous.clear()

    def disable_all(self) -> None:
        for system in list(self._systems):
            system.disable_motors()

    def _on_signal(self, signum: int, frame: types.FrameType | None) -> None:
        worker = threading.Thread(target=self.disable_all, name="sito-disable", daemon=True)
        worker.start()
        worker.join(1.0)
        previous = self._previous.get(signum, signal.SIG_DFL)
        if callable(previous):
            previous(signum, frame)
        elif previous != signal.SIG_IGN:
            signal.signal(signum, signal.SIG_DFL)
            with contextlib.suppress(OSError):
                os.kill(os.getpid(), signum)


EXIT_GUARD = ExitGuard()
