# Over 450 lines: the loop, the staged lifecycle and the switching share one lock and one state; what stands alone
# is beside it (stats, gate, rate, resources).
"""The controller manager: one fixed-rate loop, read -> update -> write, and everything around it.

- Staged start: hardware configure and activate, then the joint-state broadcaster, then ZERO_TORQUE
  active, then the other mode controllers loaded inactive, strictly in that order. A broadcaster-only run (a
  single bus, a calibration) has no mode controllers: its commands are the passive controller's (no command,
  the joints marked limp following), until a task controller claims them (``claim``: the hands-free
  calibration) and after it hands them back (``release``).
- Flat switching: ``request_mode`` (any thread) is applied at the start of the next tick, after the
  read, so the new controller activates on the live measured state. Exactly one controller is active
  and it owns every command interface (``command_owner``); the old one is deactivated before the
  new one activates.
- The one gate (control/gate.py): whatever the active controller proposes is checked once per tick, against
  the bounds and the body, and only then committed to the command the hardware components write; nothing
  else can write it. A controller's plan (STANDBY's entry trajectory) is checked when it activates.
- Fallback within one tick: a controller that raises, fails to activate (its plan refused), or whose command
  breaks a bound, is discarded for that tick and replaced (a mode by DAMPING, then ZERO_TORQUE, then a limp
  command; a task controller by the passive command) whose update runs in the same tick, so every write is
  already safe. A command the body refuses holds the arms it would drive, without a fallback.
- Telemetry: ``/control_mode`` on start and every mode switch; ``/safety_status`` (latched) whenever any
  component's, controller's or the manager's flags change.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypedDict

from humanoid_prime.config.controllers import ControllersConfig
from humanoid_prime.config.robot import Robot
from humanoid_prime.control._tick import OK
from humanoid_prime.control.controller import Controller
from humanoid_prime.control.controllers import build_controllers
from humanoid_prime.control.controllers.passive import PassiveController
from humanoid_prime.control.flags import Level, SafetyFlags
from humanoid_prime.control.gate import CommandGate
from humanoid_prime.control.hardware import HardwareComponent, Lifecycle
from humanoid_prime.control.interfaces import CommandArrays
from humanoid_prime.control.rate import Rate
from humanoid_prime.control.resources import ResourceManager
from humanoid_prime.control.stats import LoopStats
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


class ControllerManager:
    """Owns the hardware components (through the resource manager), the controllers and the loop.

    Exceptions from hardware ``read``/``write`` propagate out of ``tick``/``run``; the caller then calls
    ``shutdown`` (or uses the manager as a context manager), which leaves every device safe.
    """

    def __init__(self, robot: Robot, components: Sequence[HardwareComponent], config: ControllersConfig, *,
                 update_rate: float | None = None, topics: TopicBus | None = None,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                 broadcaster_only: bool = False, check_body: bool = True) -> None:
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
        self.passive: PassiveController | None = None  # a broadcaster-only run's command
        if broadcaster_only:
            self.passive = PassiveController()
            self.controllers[self.passive.name] = self.passive
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
        self._request: Controller | None = None
        self._reset = False
        self._refused: dict[Mode, str] = {}  # modes this run may not enter, and why
        self._tickets = 0  # mode requests made; the latest one is the one applied
        self._applying: tuple[int, Controller] | None = None  # the request applied in this tick, until it ends
        self._outcome: tuple[int, ModeOutcome] | None = None  # the latest applied request and what came of it
        self._applied = threading.Condition(self._lock)
        self._started = False
        self._closed = False
        self._last_now: float | None = None
        self._fresh_schedule = False  # the next tick starts a run's schedule: no period to measure before it
        # The one gate, between the controllers' proposal and the command the components write (read-only from
        # here on). ``check_body`` is False only where a benchmark measures what the body check costs.
        self._proposal = CommandArrays(robot.n)
        self.gate = CommandGate(robot, self._proposal, self.resources.command, self.flags, body=check_body)
        self.bounds = self.gate.bounds

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
            self._configure(self.controllers[name])
            t = self._stage(name, t)
        if self.passive is not None:
            self._configure(self.passive)
        self.resources.activate()
        t = self._stage("hardware activate", t)
        now = t if now is None else now
        self.resources.read(now)
        broadcaster = self.controllers[JOINT_STATE_BROADCASTER]
        broadcaster.on_activate(self.resources.state, now)
        broadcaster.lifecycle = Lifecycle.ACTIVE
        # No command ("none" everywhere: eRob hold their CSP targets, Sito are limp) in a broadcaster-only run.
        self._activate(self.passive if self.passive is not None else self._by_mode[Mode.ZERO_TORQUE], now)
        t = self._stage("controllers activated", t)
        self.started_at = t
        self._started = True
        self._publish_safety(now)

    def _configure(self, controller: Controller) -> None:
        controller.on_configure(self.robot, self.topics)
        controller.lifecycle = Lifecycle.INACTIVE

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
                self._request = self._by_mode[mode]
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

    def claim(self, controller: Controller) -> None:
        """Hand the commands to ``controller`` from the next tick on (any thread): a task of a broadcaster-only
        run, such as the hands-free calibration; it is configured here the first time, and its flags join
        /safety_status. Its output passes the gate like any mode's; ``release`` hands the commands back."""
        if self.passive is None:
            raise PrimeError(f"{controller.name} can only command a broadcaster-only run: this run's commands are "
                             "its modes'")
        if controller.lifecycle is Lifecycle.UNCONFIGURED:
            self._configure(controller)
            self.add_flag_source(controller)
        with self._lock:
            self._request = controller
            self._tickets += 1

    def release(self, controller: Controller) -> None:
        """``controller`` hands the commands back to the passive command from the next tick (any thread)."""
        with self._lock:
            if self.passive is not None and (self.active is controller or self._request is controller):
                self._request = self.passive
                self._tickets += 1

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
            controller, self._request = self._request, None
            reset, self._reset = self._reset, False
            if controller is not None:
                self._applying = (self._tickets, controller)
        if reset:
            self.resources.reset_faults()
            self.resets += 1
            if controller is None and self.passive is None:
                controller = self.active  # the mode is entered again (a broadcaster-only run's command goes on)
        if controller is not None:
            self.flags.clear_flag("fallback")
            self._activate(controller, now)

    def _fallback(self, controller: Controller) -> Controller | None:
        """A mode's fallback mode; a task's, the passive command; the passive command's: none."""
        if controller.mode is not None:
            fallback = FALLBACK[controller.mode]
            return None if fallback is None else self._by_mode[fallback]
        return None if controller is self.passive else self.passive

    def _activate(self, controller: Controller, now: float) -> None:
        """Make ``controller`` active on the current measured state, its plan checked by the gate; a controller
        that refuses to activate, or whose plan the gate refuses, is replaced by its fallback, recorded like any
        other fallback."""
        while True:
            self._deactivate_active()
            activated = False
            try:
                controller.on_activate(self.resources.state, now)
                activated = True
                self._check_plan(controller)
            except Exception as exc:
                if activated:
                    with contextlib.suppress(Exception):
                        controller.on_deactivate()
                fallback = self._fallback(controller)
                if fallback is None:
                    raise
                self._record_fallback(controller, fallback, f"{controller.name} could not activate: "
                                                            f"{_describe(exc)}")
                controller = fallback
                continue
            controller.lifecycle = Lifecycle.ACTIVE
            self.active = controller
            self.active_mode = controller.mode
            self.gate.bind(controller)
            if controller.mode is not None:
                self.modes_visited.append(controller.mode.value)
                self.topics.publish(CONTROL_MODE, ControlMode(controller.mode.value, controller.name, now))
            return

    def _check_plan(self, controller: Controller) -> None:
        plan = controller.planned()
        if plan is None:
            return
        found = self.gate.check_plan(*plan, self.resources.state)
        if found is not None:
            contact, share = found
            raise ControllerError(f"its path would bring {contact.words(self.gate.margin)} {share:.0%} of the way "
                                  "(the gate refused it when it was planned)")

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

    def _record_fallback(self, failed: Controller, to: Controller, reason: str) -> None:
        names = [c.mode.value if c.mode is not None else c.name for c in (failed, to)]
        self.fallbacks.append({"tick": self.tick_count, "from": names[0], "to": names[1], "reason": reason})
        self.flags.set_flag("fallback", f"{reason}; fell back from {names[0]} to {names[1]}")

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
        ticket, controller = self._applying
        self._applying = None
        requested = controller.mode
        if requested is None:
            return  # a task's claim or release: no mode outcome to tell
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
        gate = self.gate
        gate.propose()
        reason = self._run_active(now, dt)
        while reason is not None:
            failed = self.active
            assert failed is not None  # tick() updates only while a controller is active
            fallback = self._fallback(failed)
            if fallback is None:
                # Last resort: limp on every joint, target left on the last valid command.
                self._record_fallback(failed, failed, f"{reason}; writing a limp command")
                gate.propose()
                self._proposal.data[1:] = 0.0
                break
            self._record_fallback(failed, fallback, reason)
            self._activate(fallback, now)
            gate.propose()
            reason = self._run_active(now, dt)
        refused = gate.check_body(self.resources.state, self.tick_count)
        active = self.active
        if refused is not None and active is not None:
            try:
                active.on_refused(refused.words(gate.margin), gate.held)
            except Exception as exc:
                self.flags.set_flag("refused_hook", f"{active.name} failed to take a refusal: {_describe(exc)}",
                                    Level.WARN)
        gate.commit()

    def _run_active(self, now: float, dt: float) -> str | None:
        controller = self.active
        assert controller is not None  # as in _update
        try:
            controller.update(now, dt, self.resources.state, self._proposal)
        except Exception as exc:
            return f"{controller.name}: {_describe(exc)}"
        found = self.gate.check_bounds()  # the bounds (control/gate.py), clipping within the margin in place
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
