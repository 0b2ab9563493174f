"""The controller manager: one fixed-rate loop, read -> update -> write, and everything around it.

- Staged start: hardware configure and activate, then the joint-state broadcaster, then ZERO_TORQUE
  active, then the other mode controllers loaded inactive, strictly in that order.
- Flat switching: ``request_mode`` (any thread) is applied at the start of the next tick, after the
  read, so the new controller activates on the live measured state. Exactly one mode controller is
  active and it owns every command interface (``command_owner``); the old one is deactivated before the
  new one activates.
- Fallback within one tick: a mode controller that raises, or whose command fails the output check,
  is discarded for that tick and replaced (DAMPING, then ZERO_TORQUE, then a limp command) whose
  update runs in the same tick, so every write is already safe.
- Telemetry: ``/control_mode`` on start and every switch; ``/safety_status`` (latched) whenever any
  component's, controller's or the manager's flags change.

Output check (every tick): the command bounds of control/bounds.py, the same for every source. A target up to
``POSITION_MARGIN`` beyond a limit is clipped onto it; further out, as for any other bound, the command is
rejected, because a command out of bounds is a fault of the controller, not something to correct silently.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import SupportsFloat, TypedDict

import numpy as np
import numpy.typing as npt

from humanoid_prime.config.controllers import ControllersConfig
from humanoid_prime.config.robot import Robot
from humanoid_prime.control._tick import OK, OutputCheck
from humanoid_prime.control.bounds import CommandBounds
from humanoid_prime.control.controller import Controller
from humanoid_prime.control.controllers import build_controllers
from humanoid_prime.control.flags import Level, SafetyFlags
from humanoid_prime.control.hardware import HardwareComponent, Lifecycle
from humanoid_prime.control.interfaces import CommandArrays
from humanoid_prime.control.rate import Rate
from humanoid_prime.control.resources import ResourceManager
from humanoid_prime.control.topics import CONTROL_MODE, SAFETY_STATUS, ControlMode, SafetyStatus, TopicBus
from humanoid_prime.errors import ControllerError, LifecycleError, PrimeError
from humanoid_prime.modes import JOINT_STATE_BROADCASTER, MODE_CONTROLLERS, Mode

SPIN_S = 0.0005  # the last part of each period is busy-waited: sleep() wakes up to ~0.1 ms late on Linux
FALLBACK: dict[Mode, Mode | None] = {
    Mode.LOCOMOTION: Mode.DAMPING,
    Mode.REMOTE: Mode.DAMPING,
    Mode.STANDBY: Mode.DAMPING,
    Mode.DAMPING: Mode.ZERO_TORQUE,
    Mode.ZERO_TORQUE: None,
}


# A fallback as the run's summary lists it.
Fallback = TypedDict("Fallback", {"tick": int, "from": str, "to": str, "reason": str})


@dataclass(frozen=True)
class ModeOutcome:
    """What became of a mode request, once the tick that applied it has run: the mode asked for, the mode
    active at the end of that tick, and why they differ (empty when they do not)."""

    requested: Mode
    active: Mode | None
    reason: str = ""


@dataclass
class LoopStats:
    """Tick cost (read + update + write, without the wait), the part of it spent in bus I/O (the hardware
    components' ``io_s``), and tick-to-tick period, in ring buffers."""

    period: float
    capacity: int = 1 << 16
    ticks: int = 0
    overruns: int = 0
    costs: npt.NDArray[np.float64] = field(init=False, repr=False)
    ios: npt.NDArray[np.float64] = field(init=False, repr=False)
    periods: npt.NDArray[np.float64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.costs = np.zeros(self.capacity)
        self.ios = np.zeros(self.capacity)
        self.periods = np.full(self.capacity, np.nan)
        # The tick writes through plain memoryviews of doubles: one C store each, not NumPy's item assignment.
        self._rows = tuple(a.data.cast("B").cast("d") for a in (self.costs, self.ios, self.periods))

    def record(self, cost: float, period: float, io: float = 0.0) -> None:
        """``period`` is NaN for the first tick."""
        i = self.ticks % self.capacity
        costs, ios, periods = self._rows
        costs[i] = cost
        ios[i] = io
        periods[i] = period
        self.ticks += 1

    def split_us(self) -> dict[str, dict[str, float | None]]:
        """The tick cost split in our CPU (cost minus bus I/O) and bus I/O: median, p99 and max of each."""
        k = min(self.ticks, self.capacity)
        if not k:
            empty = {"median": None, "p99": None, "max": None}
            return {"cpu": dict(empty), "io": dict(empty)}
        figures: dict[str, dict[str, float | None]] = {}
        for name, values in (("cpu", self.costs[:k] - self.ios[:k]), ("io", self.ios[:k])):
            median, p99, top = np.percentile(values, (50, 99, 100)) * 1e6
            figures[name] = {"median": round(float(median), 3), "p99": round(float(p99), 3),
                             "max": round(float(top), 3)}
        return figures

    def jitter_us(self, percentiles: tuple[float, ...]) -> dict[float, float]:
        """Percentiles of |period - nominal| in us over the last ``capacity`` ticks (empty before two ticks)."""
        k = min(self.ticks, self.capacity)
        periods = self.periods[:k]
        periods = periods[np.isfinite(periods)]
        if not periods.size:
            return {}
        values = np.percentile(np.abs(periods - self.period) * 1e6, percentiles)
        return {p: float(v) for p, v in zip(percentiles, values, strict=True)}

    def tick_us(self) -> dict[str, float | None]:
        """Tick cost median, p99 and max over the last ``capacity`` ticks, in one pass (the live table asks
        for these several times a second, from a thread that shares the interpreter with the loop)."""
        k = min(self.ticks, self.capacity)
        if not k:
            return {"median": None, "p99": None, "max": None}
        median, p99, top = np.percentile(self.costs[:k], (50, 99, 100)) * 1e6
        return {"median": round(float(median), 3), "p99": round(float(p99), 3), "max": round(float(top), 3)}

    def summary(self) -> dict[str, object]:
        """Figures over the last ``capacity`` ticks; None where there is nothing to measure yet."""
        k = min(self.ticks, self.capacity)
        periods = self.periods[:k]
        periods = periods[np.isfinite(periods)]
        jitter = self.jitter_us((99,))

        def stat(values: npt.NDArray[np.float64],
                 fn: Callable[[npt.NDArray[np.float64]], SupportsFloat]) -> float | None:
            return round(float(fn(values)), 3) if values.size else None

        return {
            "ticks": self.ticks,
            "overruns": self.overruns,
            "tick_us": self.tick_us(),
            **{f"tick_{part}_us": figures for part, figures in self.split_us().items()},
            "period_ms": {"mean": stat(periods * 1e3, np.mean)},
            "jitter_us": {"p99": round(jitter[99], 3) if jitter else None},
        }


class ControllerManager:
    """Owns the hardware components (through the resource manager), the controllers and the loop.

    Exceptions from hardware ``read``/``write`` propagate out of ``tick``/``run``; the caller then calls
    ``shutdown`` (or uses the manager as a context manager), which leaves every device safe.
    """

    def __init__(self, robot: Robot, components: Sequence[HardwareComponent], config: ControllersConfig, *,
                 update_rate: float | None = None, topics: TopicBus | None = None,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                 broadcaster_only: bool = False) -> None:
        rate = config.update_rate if update_rate is None else update_rate
        if not (math.isfinite(rate) and rate > 0):
            raise PrimeError(f"update rate must be a positive number of Hz, got {rate!r}")
        self.robot = robot
        self.config = config
        self.update_rate = float(rate)
        self.period = 1.0 / self.update_rate
        self.clock = clock
        self.sleep = sleep
        self.broadcaster_only = broadcaster_only
        self.resources = ResourceManager(robot, components, partial=broadcaster_only)
        self.topics = topics if topics is not None else TopicBus()
        self.controllers = build_controllers(robot, config)
        self.stats = LoopStats(self.period)
        self.active: Controller | None = None
        self.active_mode: Mode | None = None
        self.fallbacks: list[Fallback] = []
        self.modes_visited: list[str] = []
        self.stages: list[tuple[str, float]] = []
        self.flags = SafetyFlags("controller_manager")
        # The configuration files of the run (kind -> path, sha256, source), named in every report of it.
        self.configuration: dict[str, dict[str, object]] = {}
        self.tick_count = 0
        self.started_at: float | None = None  # the clock when ``start`` finished: the run's elapsed time counts from it
        self.resets = 0  # operator fault resets applied
        self._by_mode = {c.mode: c for c in self.controllers.values() if c.mode is not None}
        self._broadcaster = self.controllers[JOINT_STATE_BROADCASTER]
        self._flag_sources: tuple[SafetyFlags, ...] = (*self.resources.components, *self.controllers.values(),
                                                        self.flags)
        self._flags_seen = -1
        self._change_seen = -1
        self._end_of_tick: tuple[Callable[[], None], ...] = ()
        self._lock = threading.Lock()
        self._request: Mode | None = None
        self._reset = False
        self._refused: dict[Mode, str] = {}  # modes this run may not enter, and why
        self._tickets = 0  # mode requests made; the latest one is the one applied
        self._applying: tuple[int, Mode] | None = None  # the request applied in this tick, until the tick ends
        self._outcome: tuple[int, ModeOutcome] | None = None  # the latest applied request and what came of it
        self._applied = threading.Condition(self._lock)
        self._started = False
        self._closed = False
        self._last_now: float | None = None
        self._fresh_schedule = False  # the next tick starts a run's schedule: no period to measure before it
        # The per-tick command handling and output check, compiled (control/_tick), bound to the proposal,
        # the command and the bounds.
        self.bounds = CommandBounds(robot)
        self._proposal = CommandArrays(robot.n)
        self._output = OutputCheck(self._proposal.data, self.resources.command.data, self.bounds.check)

    # ---- lifecycle -------------------------------------------------------------------------------

    def start(self, now: float | None = None) -> None:
        """Hardware configure, the controllers configured, hardware activate, then the broadcaster and ZERO_TORQUE
        activated; each stage's seconds in ``stages``.
        ``now`` is the loop time of the start (default: the clock; a simulation passes its simulated time, as
        it does to ``tick``), the stamp of the first joint state, mode and status."""
        if self._started:
            raise LifecycleError("the controller manager is already started")
        t = self.clock()
        self.resources.configure()
        t = self._stage("hardware configure", t)
        # The controllers are configured (a policy loaded) before the buses go cyclic: from activation on, a
        # keeper thread feeds the drives every period, and a main thread busy in Python or C would starve it.
        names = (JOINT_STATE_BROADCASTER,) if self.broadcaster_only else (JOINT_STATE_BROADCASTER,
                                                                          *MODE_CONTROLLERS.values())
        for name in names:
            controller = self.controllers[name]
            controller.on_configure(self.robot, self.topics)
            controller.lifecycle = Lifecycle.INACTIVE
            t = self._stage(name, t)
        self.resources.activate()
        t = self._stage("hardware activate", t)
        now = t if now is None else now
        self.resources.read(now)
        if self.broadcaster_only:
            # No controller claims the commands: "no command" everywhere (NaN position, zero gains), which the
            # hardware components take as hold (eRob keeps its CSP target) and limp (Sito sends nothing).
            command = self.resources.command
            command.data[:] = 0.0
            command.position[:] = np.nan
        broadcaster = self.controllers[JOINT_STATE_BROADCASTER]
        broadcaster.on_activate(self.resources.state, now)
        broadcaster.lifecycle = Lifecycle.ACTIVE
        if not self.broadcaster_only:
            self._activate(Mode.ZERO_TORQUE, now)
        t = self._stage("controllers activated", t)
        self.started_at = t
        self._started = True
        self._publish_safety(now)

    def _stage(self, name: str, since: float) -> float:
        now = self.clock()
        self.stages.append((name, now - since))
        return now

    def shutdown(self) -> None:
        """Deactivate the active controller, then deactivate and shut down every hardware component."""
        if self._closed:
            return
        self._closed = True
        try:
            self._deactivate_active()
        finally:
            try:
                self.resources.deactivate()
            finally:
                self.resources.shutdown()

    def __enter__(self) -> ControllerManager:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    # ---- switching -------------------------------------------------------------------------------

    @property
    def flag_source_names(self) -> list[str]:
        """Every source of /safety_status flags, in order (the first part of each flag key)."""
        return [source.name for source in self._flag_sources]

    def add_end_of_tick(self, hook: Callable[[], None]) -> None:
        """Call ``hook`` at the end of every tick, after ``write()`` (it must be quick: it is part of the tick).
        Work handed to another thread from here runs while the loop waits for its next period, instead of
        competing with the tick for the interpreter."""
        self._end_of_tick = (*self._end_of_tick, hook)

    def remove_end_of_tick(self, hook: Callable[[], None]) -> None:
        self._end_of_tick = tuple(h for h in self._end_of_tick if h is not hook)

    def add_flag_source(self, source: SafetyFlags) -> None:
        """Publish ``source``'s flags on /safety_status too (e.g. the eRob impedance manager)."""
        self._flag_sources = (*self._flag_sources, source)
        self._flags_seen = -1
        self._change_seen = -1

    def refuse_modes(self, modes: Sequence[Mode], reason: str) -> None:
        """From now on, requests for ``modes`` are refused with ``reason`` (e.g. a robot that is not
        calibrated may not enter a mode that moves a joint)."""
        with self._lock:
            self._refused.update({mode: reason for mode in modes})

    def request_mode(self, mode: Mode | str) -> int:
        """Ask for ``mode`` (thread-safe); it is applied at the start of the next tick. The latest request
        wins. Requesting the active mode re-enters it (Standby restarts from the measured pose). Returns the
        request's ticket for ``wait_mode``; a mode this run refuses raises PrimeError (and is flagged)."""
        mode = mode if isinstance(mode, Mode) else Mode.parse(mode)
        if self.broadcaster_only:
            raise PrimeError("this run has only the joint-state broadcaster (a single-bus or calibration run); "
                             "no mode controller can be switched on")
        with self._lock:
            refused = self._refused.get(mode)
            if refused is None:
                self._request = mode
                self._tickets += 1
                return self._tickets
        self.flags.set_flag("refused", f"{mode.value} refused: {refused}", Level.WARN)
        raise PrimeError(f"{mode.value} refused: {refused}")

    def wait_mode(self, ticket: int, timeout: float) -> ModeOutcome | None:
        """Wait until the tick that applied request ``ticket`` (or a later one, which superseded it) has run;
        what came of it, or None if no tick applied it within ``timeout`` seconds."""
        with self._applied:
            if not self._applied.wait_for(lambda: self._outcome is not None and self._outcome[0] >= ticket,
                                          timeout):
                return None
            assert self._outcome is not None  # the wait above ended on it
            applied, outcome = self._outcome
        if applied != ticket:
            return ModeOutcome(outcome.requested, outcome.active, f"superseded by a later request for "
                                                                  f"{outcome.requested.value}")
        return outcome

    def request_reset(self) -> list[str]:
        """Ask for the operator's fault reset (thread-safe), applied at the start of the next tick: every
        hardware component clears its latched faults with that tick's write, and the active mode is entered
        again from the measured state, so a drive that comes back holds where its joint is. Returns the
        latched faults at the time of the request."""
        faults = self.resources.latched_faults()
        with self._lock:
            self._reset = True
        return faults

    def _apply_request(self, now: float) -> None:
        with self._lock:
            mode, self._request = self._request, None
            reset, self._reset = self._reset, False
            if mode is not None:
                self._applying = (self._tickets, mode)
        if reset:
            self.resources.reset_faults()
            self.resets += 1
            if mode is None:
                mode = self.active_mode  # None in a broadcaster-only run: nothing to re-enter
        if mode is not None:
            self.flags.clear_flag("fallback")
            self._activate(mode, now)

    def _activate(self, mode: Mode, now: float) -> None:
        """Make ``mode`` active on the current measured state; a controller that refuses to activate is
        replaced by its fallback, recorded like any other fallback."""
        while True:
            controller = self._by_mode[mode]
            self._deactivate_active()
            try:
                controller.on_activate(self.resources.state, now)
            except Exception as exc:
                fallback = FALLBACK[mode]
                if fallback is None:
                    raise
                self._record_fallback(mode, fallback, f"{controller.name} could not activate: {_describe(exc)}")
                mode = fallback
                continue
            controller.lifecycle = Lifecycle.ACTIVE
            self.active = controller
            self.active_mode = mode
            self.modes_visited.append(mode.value)
            self.topics.publish(CONTROL_MODE, ControlMode(mode.value, controller.name, now))
            return

    def _deactivate_active(self) -> None:
        controller = self.active
        if controller is None:
            return
        self.active = None
        self.active_mode = None
        try:
            controller.on_deactivate()
        except Exception as exc:
            self.flags.set_flag("deactivate", f"{controller.name} failed to deactivate: {_describe(exc)}")
        finally:
            controller.lifecycle = Lifecycle.INACTIVE

    @property
    def command_owner(self) -> str | None:
        """The controller that owns every command interface now; None when no controller commands (a
        broadcaster-only run, or between a deactivation and the next activation)."""
        active = self.active
        return active.name if active is not None and active.claims_commands else None

    def _record_fallback(self, failed: Mode, to: Mode, reason: str) -> None:
        self.fallbacks.append({"tick": self.tick_count, "from": failed.value, "to": to.value, "reason": reason})
        self.flags.set_flag("fallback", f"{reason}; fell back from {failed.value} to {to.value}")

    # ---- the loop --------------------------------------------------------------------------------

    def tick(self, now: float | None = None) -> None:
        """One read -> update -> write, without waiting. ``now`` defaults to the clock (simulation passes
        its own time)."""
        if not self._started or self._closed:
            raise LifecycleError("tick() needs a started, not shut down, controller manager")
        began = self.clock()
        if now is None:
            now = began
        last = self._last_now
        dt = self.period if last is None else now - last
        self._last_now = now
        resources = self.resources
        resources.read(now)
        if self._request is not None or self._reset:
            self._apply_request(now)
        self._broadcast(now, dt)
        if self.active is not None:
            self._update(now, dt)
        resources.write(now)
        self._publish_safety(now)
        if self._applying is not None:
            self._tell_outcome()
        for hook in self._end_of_tick:
            hook()
        self.tick_count += 1
        io = 0.0
        for component in resources.components:
            io += component.io_s
        fresh, self._fresh_schedule = self._fresh_schedule, False
        self.stats.record(self.clock() - began, math.nan if last is None or fresh else dt, io)

    def _tell_outcome(self) -> None:
        """The request applied in this tick has had its first update: tell ``wait_mode`` what became of it."""
        assert self._applying is not None  # tick() calls this only while a request is being applied
        ticket, requested = self._applying
        self._applying = None
        active = self.active_mode
        reason = ""
        if active is not requested:
            fallback = self.fallbacks[-1]["reason"] if self.fallbacks else "no mode controller is active"
            reason = f"fell back to {active.value if active is not None else 'a limp command'}: {fallback}"
        with self._applied:
            self._outcome = (ticket, ModeOutcome(requested, active, reason))
            self._applied.notify_all()

    def _broadcast(self, now: float, dt: float) -> None:
        broadcaster = self._broadcaster
        try:
            broadcaster.update(now, dt, self.resources.state, self._proposal)
        except Exception as exc:  # a faulty subscriber must not stop the control loop
            self.flags.set_flag("broadcast", f"{broadcaster.name} failed: {_describe(exc)}", Level.WARN)

    def _update(self, now: float, dt: float) -> None:
        output = self._output
        output.propose()
        reason = self._run_active(now, dt)
        while reason is not None:
            failed = self.active_mode
            assert failed is not None  # tick() updates only while a mode is active
            fallback = FALLBACK[failed]
            if fallback is None:
                # Last resort: limp on every joint, target left on the last valid command.
                self._record_fallback(failed, failed, f"{reason}; writing a limp command")
                output.propose()
                self._proposal.data[1:] = 0.0
                break
            self._record_fallback(failed, fallback, reason)
            self._activate(fallback, now)
            output.propose()
            reason = self._run_active(now, dt)
        output.commit()

    def _run_active(self, now: float, dt: float) -> str | None:
        controller = self.active
        assert controller is not None  # as in _update
        try:
            controller.update(now, dt, self.resources.state, self._proposal)
        except Exception as exc:
            return f"{controller.name}: {_describe(exc)}"
        found = self._output.check()  # the output check (module docstring), clipping within the margin in place
        if found == OK:
            return None
        row, col = self.bounds.check.row, self.bounds.check.col
        return f"{controller.name}: {self.bounds.refusal(found, row, col, self._proposal.data[row, col])}"

    def _publish_safety(self, now: float) -> None:
        change = SafetyFlags.last_change
        if change == self._change_seen:
            return  # no source anywhere has changed its flags since the last look
        self._change_seen = change
        version = 0
        for source in self._flag_sources:
            version += source.flags_version
        if version == self._flags_seen:
            return
        self._flags_seen = version
        flags: dict[str, str] = {}
        levels: dict[str, Level] = {}
        for source in self._flag_sources:
            for key, text in dict(source.flags).items():
                flags[f"{source.name}/{key}"] = text
                levels[f"{source.name}/{key}"] = source.levels.get(key, Level.ERROR)
        self.topics.publish(SAFETY_STATUS, SafetyStatus(ok=not flags, flags=flags, levels=levels, stamp=now))

    def run(self, duration: float | None = None, stop: threading.Event | None = None,
            on_tick: Callable[[ControllerManager], None] | None = None,
            between_ticks: Callable[[], None] | None = None) -> None:
        """Tick at ``update_rate`` until ``duration`` seconds (that many periods) have run or ``stop`` is set.
        ``between_ticks`` runs after each tick and its ``on_tick``, before the wait (housekeeping that must not
        land inside a tick, such as a garbage collection).

        Paced by ``Rate`` (its overrun policy: a tick, with ``on_tick``, that ends after the next deadline is
        counted in ``stats.overruns`` and the schedule restarts from then instead of bursting to catch up);
        the last ``SPIN_S`` of each period is busy-waited.
        """
        if not self._started:
            self.start()
        total = None if duration is None else max(1, round(duration * self.update_rate))
        rate = Rate(self.update_rate, clock=self.clock, sleep=self.sleep, spin_s=SPIN_S)
        self._fresh_schedule = True
        k = 0
        while (total is None or k < total) and not (stop is not None and stop.is_set()):
            if not rate.wait():
                self.stats.overruns += 1
            self.tick()
            if on_tick is not None:
                on_tick(self)
            if between_ticks is not None:
                between_ticks()
            k += 1
        if k and rate.deadline is not None and self.clock() > rate.deadline + self.period:
            self.stats.overruns += 1  # the last tick overran too


def _describe(exc: Exception) -> str:
    """A ControllerError speaks for itself; anything else is a bug, named by its type."""
    return str(exc) if isinstance(exc, ControllerError) else f"{type(exc).__name__}: {exc}"
