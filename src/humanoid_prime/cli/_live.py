"""What an operator sees and presses while a controller manager runs: a live terminal table, a
progress line per mode when the output is not a terminal, and mode keys read from the keyboard.

Nothing here knows what drives the manager (simulation or the real buses); a caller adds its own
status line through ``status``.
"""

from __future__ import annotations

import contextlib
import os
import select
import sys
import threading
from collections.abc import Callable
from typing import Any, TextIO

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from humanoid_prime.control.flags import Level
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import SAFETY_STATUS
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.readout import LoopReadout

# As a gamepad would: one key per mode, in the order of the mode ladder.
MODE_KEYS: dict[str, Mode] = {"1": Mode.ZERO_TORQUE, "2": Mode.DAMPING, "3": Mode.STANDBY,
                              "4": Mode.LOCOMOTION, "5": Mode.REMOTE}
QUIT_KEYS = ("q", "Q")
RESET_KEYS = ("r", "R")  # the operator's fault reset
NUMBER_COLUMNS = ("q rad", "qd rad/s", "tau Nm", "q_cmd rad", "kp", "kd")
MODE_KEY_HELP = "  ".join(f"{key} {mode.value}" for key, mode in MODE_KEYS.items())


def key_help(modes: bool, reset: bool) -> str:
    """The keys line of the live table: the mode keys, the fault reset where faults latch, quit."""
    return "  ".join([*([MODE_KEY_HELP] if modes else []), *(["r reset faults"] if reset else []), "q quit"])


def _micros(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def flag_lines(manager: ControllerManager) -> list[Text]:
    """The safety flags standing now, errors in red and warnings in yellow, one line each."""
    status = manager.topics.latest(SAFETY_STATUS)
    if status is None or not status.flags:
        return []
    return [Text(f"{status.levels.get(key, Level.ERROR).name:<5} {key}: {text}",
                 style="bold red" if status.levels.get(key, Level.ERROR) is Level.ERROR else "yellow")
            for key, text in sorted(status.flags.items(), key=lambda item: -status.levels.get(item[0], Level.ERROR))]


def config_lines(manager: ControllerManager) -> list[Text]:
    """The run's configuration files, path and the start of each sha256, one dim line each."""
    return [Text(f"{kind:<11} {entry.get('path')}  sha256 {str(entry.get('sha256', ''))[:12]}", style="dim")
            for kind, entry in manager.configuration.items()]


def loop_line(manager: ControllerManager) -> str:
    """Tick count, tick cost, overruns, fallbacks and the commands the body check refused in one line."""
    stats = manager.stats
    tick = stats.tick_us()
    refused = manager.gate.refused
    last = refused.last
    where = f" (last: {last.body1}/{last.body2} {last.distance:.3f} m)" if last is not None else ""
    return (f"ticks {stats.ticks}  tick {_micros(tick['median'])}/{_micros(tick['p99'])}/{_micros(tick['max'])} us "
            f"med/p99/max  overruns {stats.overruns}  fallbacks {len(manager.fallbacks)}  refused "
            f"{refused.count}{where}")


class LiveTable:
    """A rich Live table of the mode, the time run and the loop rate, every joint's q / qd / tau and command with
    its drive's statusword, CiA402 state and AL state ("—" where a joint has no such drive), and the loop timing.

    Rendering runs in rich's refresh thread from snapshots of the arrays (``LoopReadout``), so the control loop
    never waits for the terminal.
    """

    def __init__(self, manager: ControllerManager, *, console: Console | None = None,
                 status: Callable[[], str] | None = None, keys: bool = False, reset_key: bool = False,
                 refresh_per_second: float = 8.0) -> None:
        self.manager = manager
        self.console = console if console is not None else Console()
        self.status = status
        self.keys = keys
        self.reset_key = reset_key
        self.note = ""
        self.readout = LoopReadout(manager)
        self._live = Live(get_renderable=self.render, console=self.console, refresh_per_second=refresh_per_second,
                          redirect_stdout=False, redirect_stderr=False)

    def render(self) -> Group:
        manager = self.manager
        state = manager.resources.state.data.copy()
        command = manager.resources.command.data.copy()
        readout = self.readout.read()
        mode = manager.active_mode.value if manager.active_mode is not None else "-"
        table = Table(box=None, pad_edge=False, header_style="bold")
        for column in ("joint", "bus", "q rad", "qd rad/s", "tau Nm", "q_cmd rad", "kp", "kd", "statusword", "drive",
                       "AL"):
            table.add_column(column, justify="right" if column in NUMBER_COLUMNS else "left")
        for joint in manager.robot.joints:
            i = joint.index
            drive = readout.words(joint.name)
            table.add_row(joint.name, joint.family, f"{state[0, i]:+.3f}", f"{state[1, i]:+.3f}", f"{state[2, i]:+.2f}",
                          f"{command[0, i]:+.3f}", f"{command[3, i]:.1f}", f"{command[4, i]:.1f}", drive.statusword,
                          drive.state, drive.al_state)
        header = Text.assemble(("mode ", "bold"), (mode, "bold cyan"))
        if self.status is not None:
            header.append(f"   {self.status()}")
        parts: list[Any] = [header, Text(readout.loop_words()), *config_lines(manager), Text(loop_line(manager)),
                            *flag_lines(manager), table]
        if self.keys or self.reset_key:
            note = f"   [{self.note}]" if self.note else ""
            parts.append(Text(f"keys: {key_help(self.keys, self.reset_key)}{note}", style="dim"))
        return Group(*parts)

    def __enter__(self) -> LiveTable:
        self._live.start(refresh=True)
        return self

    def __exit__(self, *exc: object) -> None:
        self._live.stop()


class ProgressLines:
    """One compact line whenever the active mode changes (for logs and pipes)."""

    def __init__(self, manager: ControllerManager, *, stream: TextIO | None = None,
                 clock: Callable[[], float] | None = None) -> None:
        self.manager = manager
        self.stream = stream if stream is not None else sys.stdout
        self.clock = clock
        self._mode: Mode | None = None

    def poll(self) -> None:
        """Cheap enough for every tick: prints only on a change of mode."""
        mode = self.manager.active_mode
        if mode is self._mode:
            return
        self._mode = mode
        when = f"{self.clock():7.2f} s  " if self.clock is not None else ""
        name = mode.value if mode is not None else "-"
        print(f"{when}{name:<11}  {loop_line(self.manager)}", file=self.stream, flush=True)


class ModeKeys:
    """Reads single key presses in a thread (terminal in cbreak mode) and turns them into requests.

    Active only when ``stream`` is a terminal. The terminal settings are restored when the context
    exits, whatever the reason.
    """

    def __init__(self, on_mode: Callable[[Mode], None], on_quit: Callable[[], None], *,
                 on_reset: Callable[[], object] | None = None, stream: TextIO | None = None,
                 extra: dict[str, Callable[[], None]] | None = None) -> None:
        self.on_mode = on_mode
        self.on_quit = on_quit
        self.on_reset = on_reset
        self.extra = dict(extra or {})  # further keys of the command (e.g. n: next phase)
        self.stream = stream if stream is not None else sys.stdin
        self.active = False
        self._saved: list[Any] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> ModeKeys:
        try:
            fd = self.stream.fileno()
        except (AttributeError, OSError, ValueError):
            return self
        if not os.isatty(fd):
            return self
        import termios
        import tty

        self._saved = termios.tcgetattr(fd)
        try:
            tty.setcbreak(fd)
            self._thread = threading.Thread(target=self._read, args=(fd,), name="mode-keys", daemon=True)
            self._thread.start()
        except BaseException:
            self._restore(fd)
            raise
        self.active = True
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        if self._saved is not None:
            self._restore(self.stream.fileno())
        self.active = False

    def _restore(self, fd: int) -> None:
        import termios

        with contextlib.suppress(termios.error, OSError):
            termios.tcsetattr(fd, termios.TCSADRAIN, self._saved)
        self._saved = None

    def _read(self, fd: int) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([fd], [], [], 0.1)
                if not ready:
                    continue
                key = os.read(fd, 1).decode("utf-8", "ignore")
            except OSError:
                return
            if not key:
                return
            self.press(key)

    def press(self, key: str) -> None:
        """Act on one key, as if it had been typed."""
        if key in QUIT_KEYS:
            self.on_quit()
        elif key in MODE_KEYS:
            with contextlib.suppress(PrimeError):  # a refused mode is flagged on /safety_status, shown above
                self.on_mode(MODE_KEYS[key])
        elif key in RESET_KEYS and self.on_reset is not None:
            self.on_reset()
        elif key in self.extra:
            self.extra[key]()



class Working:
    """A live status line on a terminal for work without a live table (bring-up, verification, benchmarks): a
    spinner, what is being done, how far (``total`` steps, if known) and the time it has taken. Nothing is drawn
    when the console is not a terminal; the line goes away when the work ends."""

    def __init__(self, console: Console, description: str, total: float | None = None) -> None:
        from rich.progress import BarColumn, Progress, SpinnerColumn, TaskProgressColumn, TextColumn, TimeElapsedColumn

        columns: list[Any] = [SpinnerColumn(), TextColumn("{task.description}")]
        if total is not None:
            columns += [BarColumn(), TaskProgressColumn()]
        columns.append(TimeElapsedColumn())
        self.progress = Progress(*columns, console=console, transient=True, disable=not console.is_terminal)
        self.task = self.progress.add_task(description, total=total)

    def update(self, description: str | None = None, completed: float | None = None) -> None:
        self.progress.update(self.task, description=description, completed=completed)

    def __enter__(self) -> Working:
        self.progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.progress.stop()
