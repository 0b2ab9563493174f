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
by a worker thread, newest first (an intermediate mode nobody is in any more is skipped).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Protocol, TypedDict, TypeVar, cast

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.flags import Level, SafetyFlags
from humanoid_prime.control.topics import CONTROL_MODE, JOINT_STATES, ControlMode, TopicBus
from humanoid_prime.drivers.erob.gains import ErobRegisters, following_window_counts, gains_to_registers, write_order
from humanoid_prime.drivers.erob.objects import (
    BUS_GAIN_GATE,
    FOLLOWING_ERROR_WINDOW,
    POS_LOOP_GAIN,
    VEL_LOOP_GAIN,
    VEL_LOOP_INTEGRAL,
)
from humanoid_prime.drivers.ethercat.priority import HELPER_PRIORITY, raise_thread
from humanoid_prime.drivers.ethercat.ring import SlaveInfo
from humanoid_prime.drivers.ethercat.sdo_client import SdoClient, SizedSdo
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode

_T = TypeVar("_T")


class SlaveSwitchDict(TypedDict):
    """``SlaveSwitch.as_dict``: one slave's part of a switch, in the reports and the control socket's answer."""

    joint: str
    position: int
    written: dict[str, int]
    read_back: dict[str, int] | None
    retries: int
    seconds: float
    al_state: str | None
    ok: bool
    problem: str | None


class SwitchReportDict(TypedDict):
    """``SwitchReport.as_dict``."""

    mode: str
    wall_seconds: float
    skew_seconds: float
    retries: int
    together: bool
    ok: bool
    read_back: str  # "done" or "pending"
    failed: dict[str, str]  # joint -> its problem
    slaves: list[SlaveSwitchDict]


@dataclass
class SlaveSwitch:
    """One slave's part of a mode switch: what was written, when it finished, how it ended, its AL state read right
    after the switch, and what its registers read back afterwards (filled in by the background read-back)."""

    position: int
    joint: str
    writes: tuple[tuple[str, int], ...]
    retries: int
    finished_s: float  # seconds after the switch started
    error: str | None = None
    mode: str = ""
    al_state: str | None = None  # None: not read (no ring states where the manager's SDOs go)
    read_back: dict[str, int] | None = None  # pos_reg, vel_reg, integral as the drive holds them
    read_back_error: str | None = None  # why they could not be read, or how they differ from what was written

    @property
    def problem(self) -> str | None:
        """Why this slave's part of the switch is not ok (None: it is, as far as known yet)."""
        if self.error:
            return self.error
        if self.al_state is not None and self.al_state != "OP":
            return f"{self.mode} switch: the slave is in {self.al_state} after it, not OP"
        return self.read_back_error

    def as_dict(self) -> SlaveSwitchDict:
        return {"joint": self.joint, "position": self.position, "written": dict(self.writes),
                "read_back": self.read_back, "retries": self.retries, "seconds": self.finished_s,
                "al_state": self.al_state, "ok": self.problem is None, "problem": self.problem}


@dataclass
class SwitchReport:
    mode: str
    wall_seconds: float
    skew_seconds: float
    retries: int
    slaves: tuple[SlaveSwitch, ...]
    together: bool  # every slave met the others before its last write (``Rendezvous``)
    checked: threading.Event = field(default_factory=threading.Event, repr=False)  # the read-back is done

    @property
    def ok(self) -> bool:
        """Every slave written, in OP after the switch, and (once read back) holding what was written."""
        return all(s.problem is None for s in self.slaves)

    def as_dict(self) -> SwitchReportDict:
        return {
            "mode": self.mode,
            "wall_seconds": self.wall_seconds,
            "skew_seconds": self.skew_seconds,
            "retries": self.retries,
            "together": self.together,
            "ok": self.ok,
            "read_back": "done" if self.checked.is_set() else "pending",
            "failed": {s.joint: s.problem for s in self.slaves if s.problem},
            "slaves": [s.as_dict() for s in self.slaves],
        }


RETRY_BACKOFF_S = 0.005
# The longest the slaves of a switch wait for the slowest before their last write: one tick at 50 Hz, the time a
# whole switch is allowed. A slave that is retrying or gone lets the others go after that.
RENDEZVOUS_S = 0.02
# While a held drive waits for its settings (after a failed restore too), the worker also looks this often.
# Otherwise it sleeps until a mode change or the EtherCAT side's word that a held drive waits: a thread that wakes
# on a timer can be preempted by a busy machine while it holds the interpreter, and the control loop then waits.
RESTORE_RETRY_S = 0.5
_RESTORE = "restore"  # on the worker's queue: look for held drives whose settings wait
# The following-error window admits this much more than the sag of a joint holding its effort limit at the
# stiffest mode's nominal kp: the drive realises about 0.7x the nominal stiffness (DESIGN §2), 1/0.7 = 1.43.
WINDOW = (FOLLOWING_ERROR_WINDOW, 0x00)

_NAMES = {POS_LOOP_GAIN: "pos_reg", VEL_LOOP_GAIN: "vel_reg", VEL_LOOP_INTEGRAL: "integral"}
_LOGGED = {**_NAMES, BUS_GAIN_GATE: "gate", (FOLLOWING_ERROR_WINDOW, 0x00): "following_window"}


class DroppedDrives(Protocol):
    """The drives held disabled after their slave dropped out (``EthercatSystem``): which wait, back in OP,
    for their settings, and the word that they are restored."""

    on_restore_needed: Callable[[], None] | None  # set by the manager; called when a held drive may wait

    def awaiting_restore(self) -> list[tuple[int, int]]: ...  # (ring position, times its slave left OP)

    def restore_pending(self) -> list[int]: ...

    def settings_restored(self, position: int, left_op: int) -> None: ...


class Rendezvous:
    """Where the workers of one parallel switch meet before each one's last write.

    Ten workers started together do not start together: on two cores the last one starts milliseconds after the
    first, and the first may have finished by then. Met before the last write, they send it within a
    fraction of that (the skew of ``prime bench``). ``meet`` returns for everybody once every party has
    arrived, or once ``timeout`` has passed since the first waited; ``together`` says which.

    It costs wall time: the first drive's new gains wait for the slowest worker's earlier writes. On the emulated
    robot with frames polled (48 switches each way) the skew's median fell from 6.9 to 5.0 ms and the wall's rose
    from 11.2 to 14.7 ms; switches within both targets (skew <= 5 ms, wall <= 20 ms) went from 7 to 26.
    """

    def __init__(self, parties: int, timeout: float = RENDEZVOUS_S) -> None:
        self._barrier = threading.Barrier(parties, timeout=timeout) if parties > 1 else None
        self.together = True

    def meet(self) -> None:
        if self._barrier is None:
            return
        try:
            self._barrier.wait()
        except threading.BrokenBarrierError:  # the wait ran out; late arrivals find the barrier broken at once
            self.together = False


@dataclass
class _Slave:
    joint: str
    position: int
    kt: float
    gear: float
    window_counts: int | None  # the following-error window this run needs; None: leave the drive's
    registers: ErobRegisters | None = None  # what the drive holds now; None = unknown
    gate_armed: bool = False
    factory_window: int | None = None  # the drive's own window, put back on close
    written: int = 0  # gain writes so far: a read-back that finds this moved on is for an older switch
    lock: threading.Lock = field(default_factory=threading.Lock)


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
        self.sdo = sdo
        self.states = states if states is not None else (
            cast(RingStates, sdo) if callable(getattr(sdo, "read_states", None)) else None)
        self.parallel = parallel
        self.retries = retries
        self.clock = clock
        self.rendezvous_s = rendezvous_s
        self.mode_gains = dict(mode_gains)
        self.slaves = [_Slave(j, hw.erob_slaves[j], hw.erob_kt[j], hw.erob_gear[j],
                              following_window_counts(robot.joints[robot.index(j)].effort_limit, mode_gains))
                       for j in hw.erob_joints]
        self.objects = SizedSdo(sdo)
        self.targets = {
            mode: {s.position: gains_to_registers(kp, kd, kt=s.kt, gear=s.gear,
                                                  efficiency=hw.erob_torque_efficiency[s.joint])
                   for s in self.slaves}
            for mode, (kp, kd) in self.mode_gains.items()
        }
        self.reports: list[SwitchReport] = []
        self.restored: list[tuple[float, str]] = []  # (time, joint): a slave back from a drop, its settings restored
        self.armed = False
        self.mode: Mode | None = None  # the mode whose gains were last applied
        self._by_position = {s.position: s for s in self.slaves}
        self._dropped: DroppedDrives | None = None
        self.sdo_log: list[tuple[float, int, str, int]] = []  # (t, position, register, value), for reports
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
        self._closing = False
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

    # ------------------------------------------------------------------------------------- bus
    def _write(self, slave: _Slave, address: tuple[int, int], value: int) -> int:
        """Write one object with bounded retries; returns the retries used, raises the last error."""
        for attempt in range(self.retries + 1):
            try:
                self.objects.write(slave.position, address, value)
                self.sdo_log.append((self.clock(), slave.position, _LOGGED[address], value))
                return attempt
            except Exception:
                if attempt == self.retries:
                    raise
                time.sleep(RETRY_BACKOFF_S * (attempt + 1))  # a recovering slave needs a moment, not a burst
        return self.retries

    def _read_registers(self, slave: _Slave) -> ErobRegisters:
        read = self.objects.read
        return ErobRegisters(pos_reg=read(slave.position, POS_LOOP_GAIN), vel_reg=read(slave.position, VEL_LOOP_GAIN),
                             integral=read(slave.position, VEL_LOOP_INTEGRAL))

    def _each(self, fn: Callable[[_Slave], _T]) -> list[_T]:
        if self._pool is not None:
            return list(self._pool.map(fn, self.slaves))
        return [fn(s) for s in self.slaves]

    def arm(self) -> None:
        """On every slave: the following-error window first, then the gate to 1, then learn what the gain
        registers hold. Nothing once ``close`` has begun."""
        if self._closing:
            return
        self.armed = True  # from here on, close() resets the gate and the window on every slave
        for slave, problem in zip(self.slaves, self._each(self._arm_one), strict=True):
            self._set_flag(f"erob/impedance/ring{slave.position}", problem)

    def _arm_one(self, slave: _Slave, again: bool = False) -> tuple[str, Level] | None:
        """The window, then the gate; ``again`` for a slave whose drive may have lost both (back from a drop)."""
        with slave.lock:
            if self._closing:  # close() resets this slave after us, or has already: arm nothing
                return None
            where = f"{slave.joint} (ring {slave.position})"
            try:
                if slave.window_counts is not None and (slave.factory_window is None or again):
                    if slave.factory_window is None:
                        slave.factory_window = self.objects.read(slave.position, WINDOW)
                    self._write(slave, WINDOW, max(slave.window_counts, slave.factory_window))
                self._write(slave, BUS_GAIN_GATE, 1)
            except Exception as exc:
                slave.registers = None
                return f"{where}: gate not armed, no gains will be written until it is: {exc}", Level.ERROR
            slave.gate_armed = True
            try:
                slave.registers = self._read_registers(slave)
            except Exception as exc:  # armed; the registers are unknown, so the next switch writes all three
                slave.registers = None
                return f"{where}: gate armed, gain registers not read back ({exc}); all three will be written", \
                    Level.WARN
        return None

    def apply(self, mode: Mode) -> SwitchReport:
        """Write ``mode``'s registers to every slave and report the switch."""
        if not self.armed:
            raise PrimeError("eRob impedance manager: gains written before the gate was armed")
        with self._busy:
            start = self.clock()
            targets = self.targets[mode]

            # Each worker arrives once: before its last write, or on its way out (nothing to write, or failed).
            rendezvous = Rendezvous(len(self.slaves) if self._pool is not None else 1, self.rendezvous_s)

            def switch_one(slave: _Slave) -> SlaveSwitch:
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

            def switch_slave(slave: _Slave, meet: Callable[[], None]) -> SlaveSwitch:
                new = targets[slave.position]
                if not slave.gate_armed:  # gain writes are ignored until the gate is 1: arm it first
                    problem = self._arm_one(slave)
                    if problem is not None and problem[1] is Level.ERROR:
                        return SlaveSwitch(slave.position, slave.joint, (), 0, self.clock() - start,
                                           f"{mode.value} gains not applied: {problem[0]}", mode.value)
                    if not slave.gate_armed:
                        return SlaveSwitch(slave.position, slave.joint, (), 0, self.clock() - start,
                                           f"{mode.value} gains not applied: the manager is closing", mode.value)
                written, retries, error = self._write_gains(slave, mode, new, before_last=meet)
                return SlaveSwitch(slave.position, slave.joint, written, retries, self.clock() - start, error,
                                   mode.value)

            self.mode = mode
            results = [r for r in self._each(switch_one) if isinstance(r, SlaveSwitch)]
            finished = [r.finished_s for r in results]
            report = SwitchReport(
                mode=mode.value,
                wall_seconds=max(finished, default=0.0),
                skew_seconds=(max(finished) - min(finished)) if finished else 0.0,
                retries=sum(r.retries for r in results),
                slaves=tuple(results),
                together=rendezvous.together,
            )
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
        try:
            found = {s.position: s for s in self.states.read_states()}
        except Exception as exc:  # the states could not be read: not confirmed, said as such
            for r in report.slaves:
                r.al_state = f"unknown (the AL states could not be read: {exc})"
            return
        for r in report.slaves:
            info = found.get(r.position)
            r.al_state = info.state_text if info is not None else "not found on the ring"

    def _flag(self, report: SwitchReport) -> None:
        for r in report.slaves:
            problem = r.problem
            self._set_flag(f"erob/impedance/ring{r.position}",
                           (f"{r.joint} (ring {r.position}): {problem}", Level.ERROR) if problem else None)

    def _read_back(self, report: SwitchReport) -> None:
        """Read every written slave's gain registers back, in the background: the switch does not wait for it. A
        slave whose drive holds other values is flagged, and its registers count as unknown (the next switch
        writes all three)."""
        written = {s.position: s.written for s in self.slaves}

        def check(r: SlaveSwitch) -> None:
            slave = self._by_position[r.position]
            with slave.lock:
                if slave.written != written[r.position]:
                    return  # a later switch wrote it meanwhile: its own read-back checks it
                try:
                    held = self._read_registers(slave)
                except Exception as exc:
                    r.read_back_error = f"gains not read back: {exc}"
                    return
                r.read_back = {"pos_reg": held.pos_reg, "vel_reg": held.vel_reg, "integral": held.integral}
                want = self.targets[Mode(report.mode)][r.position]
                if held != want:
                    slave.registers = None
                    r.read_back_error = (f"{report.mode} switch: gains read back as {r.read_back}, not "
                                         f"{dict(pos_reg=want.pos_reg, vel_reg=want.vel_reg, integral=want.integral)}")

        def check_all() -> None:
            raise_thread(HELPER_PRIORITY)
            try:
                targets = [r for r in report.slaves if r.error is None and not self._closing]
                if self._checks is not None:
                    list(self._checks.map(check, targets))
                else:
                    for r in targets:
                        check(r)
                if any(r.read_back_error for r in targets):
                    self._flag(report)
            finally:
                report.checked.set()

        if self._closing:
            report.checked.set()
            return
        self._pending = [r for r in self._pending if not r.checked.is_set()] + [report]
        threading.Thread(target=check_all, name="erob-read-back", daemon=True).start()

    def _write_gains(self, slave: _Slave, mode: Mode, new: ErobRegisters,
                     before_last: Callable[[], None] | None = None
                     ) -> tuple[tuple[tuple[str, int], ...], int, str | None]:
        """``mode``'s registers to one armed slave, only those that change, in the safe order: (what was
        written, retries, error or None). ``before_last`` runs before the last write."""
        written: list[tuple[str, int]] = []
        retries = 0
        with slave.lock:
            try:
                writes = write_order(slave.registers, new)
                for k, (address, value) in enumerate(writes):
                    if k == len(writes) - 1 and before_last is not None:
                        before_last()
                    slave.written += 1
                    retries += self._write(slave, address, value)
                    written.append((_NAMES[address], value))
                    slave.registers = _updated(slave.registers, address, value)
                slave.registers = new
                error = None
            except Exception as exc:
                done = ", ".join(name for name, _ in written) or "nothing"
                error = f"{mode.value} gains not fully applied ({done} written): {exc}"
        return tuple(written), retries, error

    def _restore_dropped(self) -> None:
        """Each slave back in OP after a drop: window, gate and the current mode's gains again, then the word
        that its drive may be released. A slave that fails keeps its drive held and is tried again."""
        if self._dropped is None or self._closing or not self.armed:
            return
        for position, left_op in self._dropped.awaiting_restore():
            slave = self._by_position.get(position)
            problem = self._restore_one(slave) if slave is not None else None
            self._set_flag(f"erob/impedance/ring{position}", problem)
            if (problem is None or problem[1] is Level.WARN) and not self._closing:
                if slave is not None:
                    self.restored.append((self.clock(), slave.joint))
                self._dropped.settings_restored(position, left_op)

    def _restore_one(self, slave: _Slave) -> tuple[str, Level] | None:
        """Window and gate again, then the current mode's gains (all three: what the drive holds is read anew)."""
        where = f"{slave.joint} (ring {slave.position})"
        with slave.lock:
            slave.gate_armed = False
            slave.registers = None  # a drive that lost power holds its factory gains: read them again
        problem = self._arm_one(slave, again=True)
        if problem is not None and problem[1] is Level.ERROR:
            return f"{problem[0]}; its drive stays held disabled", Level.ERROR
        if not slave.gate_armed:  # closing
            return None
        if self.mode is None:
            return problem
        _written, _retries, error = self._write_gains(slave, self.mode, self.targets[self.mode][slave.position])
        if error is not None:
            return f"{where}: back from a drop, {error}; its drive stays held disabled", Level.ERROR
        return None  # the registers are known again, whether or not they could be read back

    def wait_checked(self, timeout: float = 5.0) -> bool:
        """Block until every switch so far has been read back (for reports and tests); False on timeout."""
        deadline = time.monotonic() + timeout
        return all(report.checked.wait(max(deadline - time.monotonic(), 0.0)) for report in list(self.reports))

    def close(self) -> list[str]:
        """Stop following modes and reset the gate to 0 on every reachable slave; returns failures."""
        self._closing = True
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
            def reset(slave: _Slave) -> str | None:
                problems = []
                with slave.lock:
                    try:
                        self._write(slave, BUS_GAIN_GATE, 0)
                    except Exception as exc:
                        problems.append(f"gate not reset: {exc}")
                    if slave.factory_window is not None:
                        try:
                            self._write(slave, WINDOW, slave.factory_window)
                            slave.factory_window = None
                        except Exception as exc:
                            problems.append(f"following-error window not restored to {slave.factory_window}: {exc}")
                return f"{slave.joint} (ring {slave.position}): " + "; ".join(problems) if problems else None
            failures = [e for e in self._each(reset) if e]
            self.armed = False
        for pool in (self._pool, self._checks):
            if pool is not None:
                pool.shutdown(wait=True)
        self._pool = self._checks = None
        return failures

    def _set_flag(self, key: str, problem: tuple[str, Level] | None) -> None:
        if problem is None:
            self.clear_flag(key)
        else:
            self.set_flag(key, *problem)


def _updated(regs: ErobRegisters | None, address: tuple[int, int], value: int) -> ErobRegisters | None:
    if regs is None:
        return None
    return replace(regs, **{_NAMES[address]: value})
