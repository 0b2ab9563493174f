"""The eRob impedance manager: on each mode change, write that mode's loop gains over SDO.

eRob impedance is the drive's own position/velocity loop gains, reachable only by SDO, so it is
per mode, not per tick (DESIGN §2, §3). The manager:

- stays off the bus until every slave is in OP and joint states flow (mailbox traffic during DC
  activation faults a slave with 0xA000);
- widens each drive's following-error window (0x6065) to what the stiffest mode lets a loaded joint sag
  (``FOLLOWING_WINDOW_MARGIN`` times effort limit over the smallest non-zero kp), so a compliant
  impedance never trips 0x8500 by design; the drive's own window is restored on close;
- arms the bus-gain gate (0x2383 = 1) once, first, from its worker thread while the loop ticks, then reads
  back what the registers hold;
- writes every object with the size the drive reports for it (``SizedSdo``);
- on each mode change converts (kp, kd) with each joint's Kt, gear and the torque efficiency, and
  writes only the registers whose value changes, in the order that never leaves an intermediate
  pair stiffer than both modes;
- writes all slaves concurrently (one worker per slave) unless ``parallel`` is off, and holds each slave's
  last write of a switch until every slave has made its others (``Rendezvous``): the new gains then take
  effect on every drive within a few milliseconds of each other, and the wait holds a drive only in the
  intermediate pair, which is no stiffer than both modes;
- retries a failed write a bounded number of times, then raises a safety flag for that slave;
- counts a switch ``ok`` only when it is: every slave's writes went through and its AL state, read right after,
  is OP; then reads each slave's gains back in the background (the switch is not held for it) and flags a slave
  whose drive holds other values (a write that went astray, a drive that lost power meanwhile). The report says per
  slave what was written, what was read back, the retries and the wall time;
- restores a slave that dropped out (power or link) once it is back in OP: its window, its gate and the
  current mode's gains again, since a drive that lost power comes back with factory values; its drive stays
  held disabled until then (``DroppedDrives``), so a reset never enables it on gains nobody chose;
- on close resets the gate to 0 on every reachable slave, so the next bringup starts on factory gains, then
  puts back the following-error window.

Mode changes arrive on ``/control_mode`` in the control loop's thread; they are queued and applied
by a worker thread, newest first (an intermediate mode nobody is in any more is skipped). What is done on one
drive is ``DriveSettings`` (``drive_settings.py``); the parts of one switch, ``gain_switch.py``.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol, TypeVar, cast

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.flags import Level, SafetyFlags
from humanoid_prime.control.topics import CONTROL_MODE, JOINT_STATES, ControlMode, TopicBus
from humanoid_prime.drivers.erob.gains import following_window_counts, gains_to_registers
from humanoid_prime.drivers.ethercat.priority import HELPER_PRIORITY, raise_thread
from humanoid_prime.drivers.ethercat.ring import SlaveInfo
from humanoid_prime.drivers.ethercat.sdo_client import SdoClient, SizedSdo
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.drive_settings import DriveSettings, Problem
from humanoid_prime.runtime.gain_switch import RENDEZVOUS_S, Rendezvous, SlaveSwitch, SwitchReport

_T = TypeVar("_T")

# While a held drive waits for its settings (after a failed restore too), the worker also looks this often.
# Otherwise it sleeps until a mode change or the EtherCAT side's word that a held drive waits: a thread that wakes
# on a timer can be preempted by a busy machine while it holds the interpreter, and the control loop then waits.
RESTORE_RETRY_S = 0.5
# After a switch each slave's AL state is read back; a read no slave answers (a frame lost on a busy host) is made
# again, up to CONFIRM_READS times CONFIRM_PAUSE_S apart, before the switch is called not confirmed.
CONFIRM_READS = 10
CONFIRM_PAUSE_S = 0.1
_RESTORE = "restore"  # on the worker's queue: look for held drives whose settings wait


class DroppedDrives(Protocol):
    """The drives held disabled after their slave dropped out (``EthercatSystem``): which wait, back in OP,
    for their settings, and the word that they are restored."""

    on_restore_needed: Callable[[], None] | None  # set by the manager; called when a held drive may wait

    def awaiting_restore(self) -> list[tuple[int, int]]: ...  # (ring position, times its slave left OP)

    def restore_pending(self) -> list[int]: ...

    def settings_restored(self, position: int, left_op: int) -> None: ...


class RingStates(Protocol):
    """Where the manager reads the slaves' AL states after a switch (an EtherCAT master)."""

    def read_states(self) -> Sequence[SlaveInfo]: ...


class ImpedanceManager(SafetyFlags):
    """``states`` (default: ``sdo`` itself when it can read the ring's AL states) confirms each slave in OP after a
    switch."""

    def __init__(self, robot: Robot, sdo: SdoClient, mode_gains: Mapping[Mode, tuple[float, float]], *,
                 parallel: bool = True, retries: int = 3, clock: Callable[[], float] = time.monotonic,
                 rendezvous_s: float = RENDEZVOUS_S, states: RingStates | None = None) -> None:
        super().__init__("erob_impedance_manager")
        hw = robot.hardware
        self.states = states if states is not None else (
            cast(RingStates, sdo) if callable(getattr(sdo, "read_states", None)) else None)
        self.parallel = parallel
        self.clock = clock
        self.rendezvous_s = rendezvous_s
        self.mode_gains = dict(mode_gains)
        self.sdo_log: list[tuple[float, int, str, int]] = []  # (t, position, register, value), for reports
        self._closing = threading.Event()
        objects = SizedSdo(sdo)
        self.slaves = [DriveSettings(j, hw.erob_slaves[j], objects,
                                     following_window_counts(robot.joints[robot.index(j)].effort_limit, mode_gains),
                                     retries=retries, closing=self._closing, log=self.sdo_log, clock=clock)
                       for j in hw.erob_joints]
        self.targets = {
            mode: {hw.erob_slaves[j]: gains_to_registers(kp, kd, kt=hw.erob_kt[j], gear=hw.erob_gear[j],
                                                         efficiency=hw.erob_torque_efficiency[j])
                   for j in hw.erob_joints}
            for mode, (kp, kd) in self.mode_gains.items()
        }
        self.reports: list[SwitchReport] = []
        self.restored: list[tuple[float, str]] = []  # (time, joint): a slave back from a drop, its settings restored
        self.armed = False
        self.mode: Mode | None = None  # the mode whose gains were last applied
        self._by_position = {s.position: s for s in self.slaves}
        self._dropped: DroppedDrives | None = None
        # helpers of the ring: real-time below the loop where permitted (master.HELPER_PRIORITY says why)
        self._pool = ThreadPoolExecutor(max_workers=len(self.slaves), thread_name_prefix="erob-sdo",
                                        initializer=raise_thread, initargs=(HELPER_PRIORITY,)) \
            if parallel and self.slaves else None
        # the read-back after each switch, on workers of its own: the next switch never queues behind it
        self._checks = ThreadPoolExecutor(max_workers=len(self.slaves), thread_name_prefix="erob-read-back",
                                          initializer=raise_thread, initargs=(HELPER_PRIORITY,)) \
            if parallel and self.slaves else None
        self._pending: list[SwitchReport] = []
        self._queue: queue.Queue[Mode | str | None] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._joint_states_seen = threading.Event()
        self._arming_done = threading.Event()
        self._topics: TopicBus | None = None
        self._busy = threading.Lock()
        self._idle = threading.Condition()
        self._submitted = 0
        self._done = 0

    # ----------------------------------------------------------------------------------- running
    def start(self, topics: TopicBus, bus_ready: Callable[[], bool], *, timeout: float = 30.0,
              why_not_ready: Callable[[], str] | None = None, dropped: DroppedDrives | None = None) -> None:
        """Wait for OP and flowing joint states; then the worker arms the gate and follows ``/control_mode``.

        The arming's SDOs go out from the worker, so the control loop may already be feeding the drives: ten
        workers' mailbox traffic beside a keeper thread of normal priority starved its frames at 1 kHz.
        ``wait_armed`` waits for the arming. ``why_not_ready`` words what the bus lacks for the error when the
        wait runs out. With ``dropped``, the worker also restores each slave that comes back from a drop."""
        self._topics = topics
        if dropped is not None:
            self._dropped = dropped
            dropped.on_restore_needed = self.wake_for_restore
        topics.subscribe(JOINT_STATES, self._on_joint_states, latched=True)
        deadline = self.clock() + timeout
        while not (bus_ready() and self._joint_states_seen.is_set()):
            if self.clock() > deadline:
                if not self._joint_states_seen.is_set():
                    missing = "no joint states were published"
                else:
                    missing = (why_not_ready() if why_not_ready is not None else "") or "the bus was not ready"
                raise PrimeError("eRob impedance manager: the ring did not reach OP with joint states flowing "
                                 f"within {timeout:.0f} s ({missing}); no gains were written")
            time.sleep(0.005)
        topics.subscribe(CONTROL_MODE, self._on_control_mode, latched=True)
        self._worker = threading.Thread(target=self._run, name="erob-impedance", daemon=True)
        self._worker.start()

    def _on_joint_states(self, _msg: object) -> None:
        if not self._joint_states_seen.is_set():  # set() takes a lock: once is enough, not every tick
            self._joint_states_seen.set()

    def _on_control_mode(self, msg: ControlMode) -> None:
        with self._idle:
            self._submitted += 1
        self._queue.put(Mode(msg.mode))

    def _run(self) -> None:
        raise_thread(HELPER_PRIORITY)  # it holds the interpreter lock between writes (master.HELPER_PRIORITY)
        try:
            self.arm()
        except Exception as exc:  # a bug, not a bus error (those are flagged per slave): say it, keep following
            self.set_flag("erob/impedance/arming", f"gate not armed: {type(exc).__name__}: {exc}")
        finally:
            self._arming_done.set()
        while True:
            try:
                # a failed restore leaves its drive pending, so this also retries it
                waiting = self._dropped is not None and bool(self._dropped.restore_pending())
                items = [self._queue.get(timeout=RESTORE_RETRY_S if waiting else None)]
            except queue.Empty:
                items = [_RESTORE]
            while not self._queue.empty():  # coalesce: only the newest mode matters
                items.append(self._queue.get_nowait())
            if None in items:
                return
            modes = [item for item in items if isinstance(item, Mode)]
            if modes:
                try:
                    self.apply(modes[-1])
                except Exception as exc:  # keep following the mode; say what went wrong
                    self.set_flag("erob/impedance/worker",
                                  f"mode {modes[-1].value} not applied: {type(exc).__name__}: {exc}")
                finally:
                    with self._idle:
                        self._done += len(modes)
                        self._idle.notify_all()
            self._restore_dropped()

    def wake_for_restore(self) -> None:
        """Thread-safe, quick: the worker looks for held drives whose settings wait (the EtherCAT side calls it)."""
        self._queue.put(_RESTORE)

    def wait_armed(self, timeout: float = 5.0) -> bool:
        """Block until the worker has armed the gate (or found it could not); False on timeout."""
        return self._arming_done.wait(timeout)

    def wait_idle(self, timeout: float = 5.0) -> bool:
        """Block until every mode change received so far has been applied (for reports and tests)."""
        with self._idle:
            return self._idle.wait_for(lambda: self._done >= self._submitted, timeout)

    # ---------------------------------------------------------------------------------- switching
    def _each(self, fn: Callable[[DriveSettings], _T]) -> list[_T]:
        if self._pool is not None:
            return list(self._pool.map(fn, self.slaves))
        return [fn(s) for s in self.slaves]

    def arm(self) -> None:
        """On every slave: the following-error window first, then the gate to 1, then learn what the gain
        registers hold. Nothing once ``close`` has begun."""
        if self._closing.is_set():
            return
        self.armed = True  # from here on, close() resets the gate and the window on every slave
        for slave, problem in zip(self.slaves, self._each(DriveSettings.arm), strict=True):
            self._set_flag(f"erob/impedance/ring{slave.position}", problem)

    def apply(self, mode: Mode) -> SwitchReport:
        """Write ``mode``'s registers to every slave and report the switch."""
        if not self.armed:
            raise PrimeError("eRob impedance manager: gains written before the gate was armed")
        with self._busy:
            start = self.clock()
            targets = self.targets[mode]

            # Each worker arrives once: before its last write, or on its way out (nothing to write, or failed).
            rendezvous = Rendezvous(len(self.slaves) if self._pool is not None else 1, self.rendezvous_s)

            def switch_one(slave: DriveSettings) -> SlaveSwitch:
                met = False

                def meet() -> None:
                    nonlocal met
                    met = True
                    rendezvous.meet()

                try:
                    return switch_slave(slave, meet)
                finally:
                    if not met:
                        rendezvous.meet()

            def switch_slave(slave: DriveSettings, meet: Callable[[], None]) -> SlaveSwitch:
                if not slave.gate_armed:  # gain writes are ignored until the gate is 1: arm it first
                    problem = slave.arm()
                    if problem is not None and problem[1] is Level.ERROR:
                        return SlaveSwitch(slave.position, slave.joint, (), 0, self.clock() - start,
                                           f"{mode.value} gains not applied: {problem[0]}", mode.value)
                    if not slave.gate_armed:
                        return SlaveSwitch(slave.position, slave.joint, (), 0, self.clock() - start,
                                           f"{mode.value} gains not applied: the manager is closing", mode.value)
                written, retries, error = slave.write_gains(mode, targets[slave.position], before_last=meet)
                return SlaveSwitch(slave.position, slave.joint, written, retries, self.clock() - start, error,
                                   mode.value)

            self.mode = mode
            report = SwitchReport.of(mode.value, tuple(self._each(switch_one)), rendezvous.together)
            self._confirm_op(report)
            self.reports.append(report)
            self._flag(report)
            self._read_back(report)
            return report

    def _confirm_op(self, report: SwitchReport) -> None:
        """Each slave's AL state, read once the switch is done: a drive that left OP during it (its working counter
        may still look right) makes the switch not ok."""
        if self.states is None:
            return
        for _ in range(CONFIRM_READS):
            try:
                found = {s.position: s for s in self.states.read_states()}
            except Exception as exc:  # the states could not be read: not confirmed, said as such
                for r in report.slaves:
                    r.al_state = f"unknown (the AL states could not be read: {exc})"
                return
            # 0 is no state: the read's frame came back unanswered (or not at all), so it is read again
            unanswered = [r for r in report.slaves if (info := found.get(r.position)) is not None and not info.al_state]
            if not unanswered or self._closing.wait(CONFIRM_PAUSE_S):
                break
        for r in report.slaves:
            info = found.get(r.position)
            if info is None:
                r.al_state = "not found on the ring"
            elif not info.al_state:
                r.al_state = (f"unknown (it answered none of {CONFIRM_READS} reads of its AL state over "
                              f"{CONFIRM_READS * CONFIRM_PAUSE_S:g} s)")
            else:
                r.al_state = info.state_text

    def _flag(self, report: SwitchReport) -> None:
        for r in report.slaves:
            problem = r.problem
            self._set_flag(f"erob/impedance/ring{r.position}",
                           (f"{r.joint} (ring {r.position}): {problem}", Level.ERROR) if problem else None)

    def _read_back(self, report: SwitchReport) -> None:
        """Read every written slave's gain registers back, in the background: the switch does not wait for it. A
        slave whose drive holds other values is flagged (``DriveSettings.check``)."""
        written = {s.position: s.written for s in self.slaves}
        want = self.targets[Mode(report.mode)]

        def check(r: SlaveSwitch) -> None:
            self._by_position[r.position].check(r, written[r.position], want[r.position])

        def check_all() -> None:
            raise_thread(HELPER_PRIORITY)
            try:
                targets = [r for r in report.slaves if r.error is None and not self._closing.is_set()]
                if self._checks is not None:
                    list(self._checks.map(check, targets))
                else:
                    for r in targets:
                        check(r)
                if any(r.read_back_error for r in targets):
                    self._flag(report)
            finally:
                report.checked.set()

        if self._closing.is_set():
            report.checked.set()
            return
        self._pending = [r for r in self._pending if not r.checked.is_set()] + [report]
        threading.Thread(target=check_all, name="erob-read-back", daemon=True).start()

    def _restore_dropped(self) -> None:
        """Each slave back in OP after a drop: window, gate and the current mode's gains again, then the word
        that its drive may be released. A slave that fails keeps its drive held and is tried again."""
        if self._dropped is None or self._closing.is_set() or not self.armed:
            return
        current = (self.mode, self.targets[self.mode]) if self.mode is not None else None
        for position, left_op in self._dropped.awaiting_restore():
            slave = self._by_position.get(position)
            problem = None
            if slave is not None:
                problem = slave.restore((current[0], current[1][position]) if current is not None else None)
            self._set_flag(f"erob/impedance/ring{position}", problem)
            if (problem is None or problem[1] is Level.WARN) and not self._closing.is_set():
                if slave is not None:
                    self.restored.append((self.clock(), slave.joint))
                self._dropped.settings_restored(position, left_op)

    def wait_checked(self, timeout: float = 5.0) -> bool:
        """Block until every switch so far has been read back (for reports and tests); False on timeout."""
        deadline = time.monotonic() + timeout
        return all(report.checked.wait(max(deadline - time.monotonic(), 0.0)) for report in list(self.reports))

    def close(self) -> list[str]:
        """Stop following modes and reset the gate to 0 on every reachable slave; returns failures."""
        self._closing.set()
        if self._worker is not None:
            self._queue.put(None)
            self._worker.join(timeout=5.0)
            self._worker = None
        for report in self._pending:  # a read-back under way finishes before the gate goes back to 0
            report.checked.wait(5.0)
        if self._topics is not None:
            self._topics.unsubscribe(CONTROL_MODE, self._on_control_mode)
            self._topics.unsubscribe(JOINT_STATES, self._on_joint_states)
        failures: list[str] = []
        if self.armed:
            failures = [e for e in self._each(DriveSettings.reset) if e]
            self.armed = False
        for pool in (self._pool, self._checks):
            if pool is not None:
                pool.shutdown(wait=True)
        self._pool = self._checks = None
        return failures

    def _set_flag(self, key: str, problem: Problem | None) -> None:
        if problem is None:
            self.clear_flag(key)
        else:
            self.set_flag(key, *problem)
