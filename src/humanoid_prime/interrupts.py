"""Ctrl-C while a command runs (``Interrupts``): KeyboardInterrupt as usual, remembered, and never lost where Python
would drop it. The entry (``humanoid_prime.__main__``) starts watching before the command line loads, so that a
Ctrl-C at any moment of a command's start-up ends it the same way: one line, exit 130."""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable
from types import FrameType

Handler = Callable[[int, FrameType | None], object] | int | signal.Handlers | None  # as signal.signal takes it


class Interrupts:
    """From its construction until ``close``: Ctrl-C raises KeyboardInterrupt as usual, and is remembered (``seen``).

    One that lands where Python reports an exception and drops it (a weakref callback, such as the one importlib
    runs as every import ends, or a ``__del__``) would be printed as a traceback and lost, and the command would go
    on: it is raised again instead, at the next call or return of the main thread, where it ends the command.
    Nothing changes off the main thread, where signals cannot be handled, or where SIGINT is not Python's default
    (e.g. ignored)."""

    def __init__(self) -> None:
        self.seen = False
        self._handler: Handler = None  # the handler replaced (None: nothing replaced)
        self._hook = sys.unraisablehook
        if threading.current_thread() is threading.main_thread() \
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self._handler = signal.signal(signal.SIGINT, self._interrupt)
            sys.unraisablehook = self._dropped

    def _interrupt(self, signum: int, frame: FrameType | None) -> None:
        self.seen = True
        raise KeyboardInterrupt

    def _dropped(self, unraisable: sys.UnraisableHookArgs) -> None:
        if not (self.seen and isinstance(unraisable.exc_value, KeyboardInterrupt)
                and threading.current_thread() is threading.main_thread() and sys.getprofile() is None):
            self._hook(unraisable)
            return
        sys.setprofile(self._raise_again)  # Python calls it at every call and return: see there

    def _raise_again(self, frame: FrameType, event: str, arg: object) -> None:
        if frame.f_code is Interrupts._dropped.__code__:  # still inside the hook, whose exceptions are dropped too
            return
        sys.setprofile(None)
        raise KeyboardInterrupt

    def close(self) -> None:
        """The handler and the hook as they were."""
        if self._handler is None:
            return
        if sys.getprofile() == self._raise_again:
            sys.setprofile(None)
        sys.unraisablehook = self._hook
        signal.signal(signal.SIGINT, self._handler)
