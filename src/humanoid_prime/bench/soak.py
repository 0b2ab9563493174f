"""The soak: the emulated robot for minutes at its control rate, cycling through all five modes with a remote
stream, while both cores are loaded and faults are injected on both buses.

It runs in-process (inside the emulation's private network namespace, as ``prime bringup --emulate`` does),
on the run path of ``prime bringup``: real-time loop, impedance manager, gate reset on the way out. A
helper thread injects one fault every ``fault_every_s`` through the virtual Prime's control socket, in
turn from ``FAULTS``; each fault states what the stack must do about it:

- ``counted``: absorbed without a flag (one lost or garbage frame), and visible in a counter;
- ``recovered``: flagged under ``flag``, then cleared by the stack itself;
- ``latched``: flagged, held until the operator's reset (which the soak sends once the ring is whole), then
  cleared (a drive fault, and a drive whose slave was lost and came back: it stays disabled until the operator
  says so);
- ``refused``: an SDO the drive aborts reaches its caller as that abort, and nothing else changes.

Each injection is judged from the run's own fault history (the summary's), and every ERROR flag that no
injection explains (a drive fault nobody injected above all) is reported as unexpected. The REMOTE stream
publishes one MIT command per tick on the remote topic, the path the DDS bridge feeds.
"""

from __future__ import annotations

import contextlib
import fnmatch
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from humanoid_prime.drivers.erob.objects import RATED_TORQUE
from humanoid_prime.drivers.ethercat.errors import SdoError
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.run import run_loop
from humanoid_prime.runtime.session import BringupOptions, claim_control_socket, open_session, plan_session

# the demonstration's order: every mode is entered from one whose pose is near its own
MODE_CYCLE = (Mode.ZERO_TORQUE, Mode.DAMPING, Mode.STANDBY, Mode.LOCOMOTION, Mode.REMOTE, Mode.STANDBY, Mode.DAMPING)
SETTLE_S = 3.0  # how long after an injection (or its end) the stack has to flag and recover
LOST_RING = 9  # the last slave: losing it leaves the rest of the line reachable
REFERENCE_RING = 0  # the first slave, the reference clock: losing it cuts the whole line off
READ_ONLY_ABORT = "0X06010002"  # CiA 301 abort: attempt to write a read-only object
VERIFY_READS = 3  # reads of the returned drive's settings, when a mode switch falls between two
RESET_APPLIED_S = 2.0  # the longest an operator's reset may wait for the loop's next tick


@dataclass
class Fault:
    name: str
    bus: str
    expect: str  # counted, recovered, latched, refused
    flag: str | None  # fnmatch pattern of the flag key it raises (None: it must raise none)
    inject: Callable[[Any, Any], Any]  # (virtual prime control, session) -> what happened
    hold_s: float = 0.0  # how long the fault lasts before ``end`` undoes it
    end: Callable[[Any], None] | None = None
    # after the operator's reset of a latched fault: what is wrong with the drive it released (None: nothing)
    verify: Callable[[Any, Any], str | None] | None = None
    also: tuple[str, ...] = ()  # flags it may raise besides ``flag`` (consequences, not surprises)
    settle_s: float = SETTLE_S  # how long after it ended the stack has to flag (and, latched, be reset)

    @property
    def patterns(self) -> tuple[str, ...]:
        """Every flag key pattern it may raise: its own, then its consequences."""
        return (*((self.flag,) if self.flag else ()), *self.also)


def _sito(joint: str, **fields: object) -> Callable[..., Any]:
    """One wrist's fault setting, as an injection (control, session) or its end (control)."""
    return lambda control, session=None: control.call("sito", joint=joint, **fields)


def _sdo_abort(control: Any, session: Any) -> str:
    """Write the read-only rated torque (0x6076) of ring 0, as a mistyped `prime ec sdo` would."""
    try:
        session.ethercat.master.sdo_write(0, RATED_TORQUE, 0, b"\x00\x00\x00\x00")
    except SdoError as exc:
        return str(exc)
    raise PrimeError("the drive accepted a write to its read-only 0x6076")


def _settings_restored(ring: int) -> Callable[[Any, Any], str | None]:
    """The check that the drive at ``ring``, returned, holds the gate and the gains of the mode the impedance
    manager applied last: a drive that lost power comes back on factory gains, and must not be enabled on them."""

    def verify(control: Any, session: Any) -> str | None:
        impedance = session.impedance
        if impedance is None or impedance.mode is None:  # no impedance manager, or no mode's gains applied yet
            return None
        for _ in range(VERIFY_READS):  # a mode switch between the two reads: read again
            impedance.wait_idle(5.0)
            mode, switches = impedance.mode, len(impedance.reports)
            drive = control.slave(ring)["drive"]
            want = impedance.targets[mode][ring]
            held = (drive["gate"], drive["pos_reg"], drive["vel_reg"], drive["integral"])
            if held == (1, want.pos_reg, want.vel_reg, want.integral):
                return None
            if len(impedance.reports) == switches:
                break
        return (f"ring {ring} was released with gate {held[0]} and registers {held[1:]}, not the gate 1 and "
                f"{mode.value}'s {(want.pos_reg, want.vel_reg, want.integral)}")

    return verify


FAULTS: tuple[Fault, ...] = (
    Fault("one EtherCAT frame lost", "ethercat", "counted", None,
          lambda c, s: c.call("drop", count=1, where="request")),
    Fault("EtherCAT replies lost, 20 frames", "ethercat", "recovered", "*/ethercat/wkc",
          lambda c, s: c.call("drop", count=20, where="reply"),
          also=("*/ethercat/ring*/lost",)),  # the supervision's state reads are lost too: "not answering"
    Fault("EtherCAT frames delayed 30 ms, 30 frames", "ethercat", "recovered", "*/ethercat/wkc",
          lambda c, s: c.call("delay", seconds=0.03, count=30), also=("*/ethercat/ring*/lost",)),
    Fault("garbage EtherCAT frames", "ethercat", "counted", None, lambda c, s: c.call("garbage", count=5)),
    # a slow drive or a busy host: mailbox replies 40 ms late, the frames that carry replies back after the 2 ms a
    # frame is given, and the whole emulator stalled for 30 ms (the cycle's frames late too)
    Fault("EtherCAT mailbox replies 40 ms late, 20 replies", "ethercat", "counted", None,
          lambda c, s: c.call("late_replies", count=20, seconds=0.04)),
    Fault("EtherCAT reply frames held 8 ms, 5 frames", "ethercat", "counted", None,
          lambda c, s: c.call("hold_reply_frames", count=5, seconds=0.008)),
    Fault("EtherCAT ring stalled 30 ms", "ethercat", "counted", None, lambda c, s: c.call("stall", seconds=0.03)),
    # back in OP once it has relocked (350 frames at the control rate: 7 s at 50 Hz), its drive held disabled
    Fault("slave lost and returned", "ethercat", "latched", f"*/ethercat/ring{LOST_RING}/disabled",
          lambda c, s: c.call("lose", position=LOST_RING), hold_s=1.0,
          end=lambda c: c.call("restore", position=LOST_RING), settle_s=15.0, verify=_settings_restored(LOST_RING),
          also=(f"*/ethercat/ring{LOST_RING}/lost", "*/ethercat/wkc",
                "*/erob/impedance/ring*")),  # a mode switch meanwhile is refused, and flagged
    # the first slave: the ring's time (the reference clock) restarts from 0 with it, and the line behind it is cut
    # meanwhile, so every other drive's watchdog runs out (0xA000, latched too); its clock is set to the time of a
    # drive that kept its own before SYNC0 starts again, and the others relock on it
    Fault("reference clock slave lost and returned", "ethercat", "latched", f"*/ethercat/ring{REFERENCE_RING}/disabled",
          lambda c, s: c.call("lose", position=REFERENCE_RING), hold_s=1.0,
          end=lambda c: c.call("restore", position=REFERENCE_RING), settle_s=20.0,
          verify=_settings_restored(REFERENCE_RING),
          also=("*/ethercat/ring*/lost", "*/ethercat/wkc", "*/ethercat/ring*/fault", "*/ethercat/ring*/disabled",
                "*/erob/impedance/ring*")),
    Fault("drive fault 0x7500", "ethercat", "latched", "*/ethercat/ring6/fault",
          lambda c, s: c.call("fault", position=6, code=0x7500)),
    Fault("SDO abort", "ethercat", "refused", None, _sdo_abort),
    Fault("silent Sito", "can", "recovered", "*/rx_timeout/*", _sito("left_wrist_roll", silent=True),
          hold_s=1.0, end=_sito("left_wrist_roll", silent=False)),
    Fault("garbage CAN frames", "can", "recovered", "*/invalid_frame", _sito("right_wrist_roll", garbage=True),
          hold_s=1.0, end=_sito("right_wrist_roll", garbage=False)),
    Fault("Sito frames dropped (30 %)", "can", "counted", None,
          _sito("right_wrist_pitch", drop_fraction=0.3), hold_s=2.0,
          end=_sito("right_wrist_pitch", drop_fraction=0.0)),
    Fault("Sito feedback 50 ms late", "can", "counted", None, _sito("left_wrist_pitch", late_s=0.05), hold_s=2.0,
          end=_sito("left_wrist_pitch", late_s=0.0)),
)


@dataclass
class Injection:
    fault: Fault
    at_s: float  # since the run began
    done_s: float = 0.0  # when the fault ended (its ``end`` ran)
    outcome: str = ""
    detail: str = ""
    flags: list[str] = field(default_factory=list)
    released_wrong: str | None = None  # what ``Fault.verify`` found wrong after the reset

    @property
    def ended_s(self) -> float:
        return self.done_s or self.at_s

    def as_dict(self) -> dict[str, Any]:
        return {"fault": self.fault.name, "bus": self.fault.bus, "expected": self.fault.expect,
                "at_s": round(self.at_s, 3),
                "outcome": self.outcome, "as_designed": self.outcome == self.fault.expect, "detail": self.detail,
                "flags": self.flags}


class Load:
    """Both cores kept busy: ``stress-ng --cpu N`` where installed, else N spinning interpreters."""

    def __init__(self, cpus: int) -> None:
        self.cpus = cpus
        if shutil.which("stress-ng"):
            self.how = f"stress-ng --cpu {cpus}"
            command = ["stress-ng", "--cpu", str(cpus), "--quiet"]
            self._processes = [subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                                start_new_session=True)]
        else:
            self.how = f"{cpus} spinning Python processes"
            self._processes = [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True)
                               for _ in range(cpus)]

    def close(self) -> None:
        for process in self._processes:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGTERM)
            process.wait(timeout=10)


class Injector(threading.Thread):
    """One fault every ``every_s`` in turn; the operator's reset for a latched one once it has been seen. With
    ``once``, one pass: after every fault has been injected once and the last has had its settle time, it ends
    the run (``stop``)."""

    def __init__(self, control: Any, session: Any, every_s: float, stop: threading.Event, run_s: float,
                 once: bool = False) -> None:
        super().__init__(name="soak-faults", daemon=True)
        self.control, self.session, self.every_s, self.stop, self.once = control, session, every_s, stop, once
        self.ends_s = self._now() + run_s  # no fault is injected that could not settle before the run ends
        self.injections: list[Injection] = []
        self.resets: list[float] = []  # when the operator's resets were sent (seconds since the run began)
        self.owed: list[Injection] = []  # latched faults not reset within their settle time: reset when whole
        self.error: str | None = None

    def _now(self) -> float:
        return time.monotonic() - self.session.plan.began

    def run(self) -> None:
        try:
            k = 0
            while not self.stop.wait(self.every_s):
                self._reset_owed()
                if self.once and k == len(FAULTS):
                    self.stop.wait(FAULTS[-1].settle_s)
                    self.stop.set()
                    return
                fault = FAULTS[k % len(FAULTS)]
                if any(owed.fault.bus == fault.bus for owed in self.owed):
                    continue  # its bus still waits for a latched fault's reset: the next fault goes onto a whole ring
                k += 1
                if self._now() + fault.hold_s + fault.settle_s + 1.0 > self.ends_s:
                    return
                injection = Injection(fault, self._now())
                self.injections.append(injection)
                result = fault.inject(self.control, self.session)
                injection.detail = result if isinstance(result, str) else ""
                if fault.hold_s and self.stop.wait(fault.hold_s):
                    fault.end(self.control)
                    return
                if fault.end is not None:
                    fault.end(self.control)
                injection.done_s = self._now()
                if fault.expect == "latched" and not self._reset_when_flagged(injection):
                    self.owed.append(injection)
        except Exception as exc:  # a control call that failed ends the soak's injections, and says why
            self.error = f"{type(exc).__name__}: {exc}"

    def _whole(self, fault: Fault) -> bool:
        """The operator resets once the ring is whole and its drives' settings are back."""
        ethercat = self.session.ethercat
        return fault.bus != "ethercat" or (ethercat.master.slave_ok.all() and not ethercat.restore_pending())

    def _flagged(self, injection: Injection, still: bool = False) -> bool:
        return any(fnmatch.fnmatch(r.key, injection.fault.flag) and r.since_s >= injection.at_s
                   and not (still and r.until_s is not None) for r in list(self.session.faults))

    def _reset(self, injection: Injection) -> None:
        """The operator's reset, and a wait until the loop has applied it: a fault injected meanwhile would be
        cleared by it, unseen."""
        manager = self.session.manager
        self.resets.append(self._now())
        applied = manager.resets
        manager.request_reset()
        deadline = time.monotonic() + RESET_APPLIED_S
        while manager.resets == applied and time.monotonic() < deadline and not self.stop.wait(0.01):
            pass
        self.stop.wait(3.0 / manager.update_rate)  # its fault-reset pulse goes out with the next writes
        if injection.fault.verify is not None:
            injection.released_wrong = injection.fault.verify(self.control, self.session)
            if injection.released_wrong:
                injection.detail = injection.released_wrong

    def _reset_when_flagged(self, injection: Injection) -> bool:
        """The reset once the fault is flagged and the ring whole, within the fault's settle time; False if the
        ring was not whole by then."""
        deadline = time.monotonic() + injection.fault.settle_s
        while time.monotonic() < deadline and not self.stop.is_set():
            if self._whole(injection.fault) and self._flagged(injection):
                self._reset(injection)
                return True
            time.sleep(0.02)
        return False

    def _reset_owed(self) -> None:
        """A latched fault whose ring took longer than its settle time to be whole (a returning slave's clock
        relocking on a loaded machine) gets its reset before the next injection, once the ring is whole, as an
        operator would give it; one whose flag another reset has cleared meanwhile is owed nothing. Until then no
        fault is injected on its bus: one injected onto a drive still held would find its flag already up."""
        for injection in list(self.owed):
            if not self._flagged(injection, still=True):
                self.owed.remove(injection)
            elif self._whole(injection.fault):
                self.owed.remove(injection)
                self._reset(injection)


def judge(injection: Injection, faults: list[Any], ended_s: float, next_at_s: float = float("inf"),
          resets: Sequence[float] = ()) -> None:
    """``injection.outcome`` from the run's fault history (module docstring) and the times the operator's
    resets were sent; a fault that must raise no flag is judged until the next injection at the latest.

    A latched flag must clear only after a reset sent since the injection: its own, or a later fault's when
    the ring took longer than the settle time to be whole again (the soak resets only a whole ring, so a drive
    whose slave relocks slowly under load waits, disabled, for the next reset)."""
    fault = injection.fault
    window_end = injection.ended_s + fault.settle_s
    if fault.flag is None:
        window_end = min(window_end, next_at_s)
        raised = [r for r in faults if injection.at_s <= r.since_s <= window_end and r.level.name == "ERROR"]
        injection.flags = [r.key for r in raised]
        if fault.expect == "refused":
            # the drive's abort, or the master's refusal while ring 0 recovers: either way nothing was written
            refused = READ_ONLY_ABORT in injection.detail.upper() or "refused:" in injection.detail
            injection.outcome = "refused" if refused and not raised else "not refused"
        else:
            injection.outcome = "counted" if not raised else "flagged"
        return
    raised = [r for r in faults if fnmatch.fnmatch(r.key, fault.flag) and injection.at_s <= r.since_s <= window_end]
    injection.flags = [r.key for r in raised]
    if not raised:
        injection.outcome = "not flagged"
    elif any(r.until_s is None for r in raised) and window_end < ended_s:
        injection.outcome = "held"  # still flagged long after it ended
    elif fault.expect == "latched":
        by_reset = all(r.until_s is None or any(injection.at_s <= t <= r.until_s for t in resets) for r in raised)
        injection.outcome = ("recovered without a reset" if not by_reset
                             else "released on settings nobody chose" if injection.released_wrong else "latched")
    else:
        injection.outcome = "recovered"


def explained(record: Any, injections: list[Injection], faults: list[Any]) -> bool:
    """A flag is explained by an injection whose flag (or a consequence of it) it matches, in its window: from
    the injection until ``SETTLE_S`` after the fault ended, or after its own flag cleared if that was later (a
    mode switch while a returned slave is still recovering is refused, as it must be)."""
    for injection in injections:
        ended = injection.ended_s
        settle = injection.fault.settle_s
        own = [r for r in faults if injection.fault.flag and fnmatch.fnmatch(r.key, injection.fault.flag)
               and injection.at_s <= r.since_s <= ended + settle]
        cleared = max((float("inf") if r.until_s is None else r.until_s for r in own), default=ended + settle)
        window_end = max(ended + settle, cleared + SETTLE_S)
        if injection.at_s <= record.since_s <= window_end and any(fnmatch.fnmatch(record.key, p)
                                                                   for p in injection.fault.patterns):
            return True
    return False


def bench_soak(minutes: float = 10.0, *, rate: float | None = None, load: bool = True, cpu: int | None = None,
               fault_every_s: float = 6.0, dwell_s: float = 10.0, faults_once: bool = False,
               report: Callable[[str], None] = print, hardware_file: str | None = None) -> dict[str, Any]:
    """Run the soak (module docstring) in this process, which must be in a private network namespace. With
    ``faults_once`` it ends after one pass of every fault (``minutes`` is then the most it may take)."""
    from humanoid_prime.sim.demo import demo_stream
    from humanoid_prime.virtual.harness import attach_virtual_prime

    options = BringupOptions(emulated=True, duration=minutes * 60.0, update_rate=rate, realtime=True, cpu=cpu,
                             hardware_file=hardware_file, control_socket=None)
    stop = threading.Event()
    emulator: dict[str, Any] = {}
    load_process = None
    with contextlib.ExitStack() as stack:
        plan = plan_session(options)
        folder = stack.enter_context(tempfile.TemporaryDirectory(prefix="prime-soak-"))
        plan.options.control_socket = os.path.join(folder, "control.sock")
        claim_control_socket(plan, stack)
        virtual = attach_virtual_prime(stack, hardware_file=hardware_file, record=emulator, avoid_cpu=cpu)
        options.interface = virtual.master_interface
        options.can_interface, options.can_channel = virtual.can_interface, virtual.can_channel
        session = open_session(plan, stack)
        manager = session.manager
        stream = demo_stream(session.robot, session.config, manager)
        if load:
            load_process = Load(os.cpu_count() or 2)
            stack.callback(load_process.close)
        injector = Injector(virtual.control, session, fault_every_s, stop, minutes * 60.0, once=faults_once)
        modes = {"next": 0, "at": 0.0}

        def on_tick(m: Any) -> None:
            now = time.monotonic()
            if now >= modes["at"]:
                m.request_mode(MODE_CYCLE[modes["next"] % len(MODE_CYCLE)])
                modes["next"] += 1
                modes["at"] = now + dwell_s
            stream.publish(now)

        report(f"soak: {minutes:g} min at {manager.update_rate:g} Hz, modes every {dwell_s:g} s, a fault every "
               f"{fault_every_s:g} s, load: {load_process.how if load_process else 'none'}")
        injector.start()
        loop_began_s = time.monotonic() - plan.began
        try:
            run_loop(session, stop, on_tick=on_tick, report=report)
        finally:
            stop.set()
            injector.join(timeout=SETTLE_S + 5.0)
        ended_s = time.monotonic() - plan.began
        injections = injector.injections
        for k, injection in enumerate(injections):
            judge(injection, session.faults, ended_s, injections[k + 1].at_s if k + 1 < len(injections) else ended_s,
                  injector.resets)
        stats = manager.stats
        ethercat, sito = session.ethercat, session.sito
        counters = {"ethercat_wkc_errors": ethercat.wkc_errors, "sito_send_failures": sito.send_failures,
                    "stream_published": stream.published, "operator_resets": manager.resets}
    summary = session.summary()  # after teardown: the end state, the gate reset
    injected = {i.fault.name for i in injector.injections}
    unexpected = [r.as_dict() for r in session.faults
                  if r.level.name == "ERROR" and not explained(r, injector.injections, session.faults)]
    k = min(stats.ticks, stats.capacity)
    periods = stats.periods[:k]
    jitter = stats.jitter_us((50, 99, 99.9, 100))
    # an overrun: a tick that took, or a period that lasted, more than twice the period
    late = np.flatnonzero((stats.costs[:k] > 2 * stats.period) | (periods > 2 * stats.period))
    since_start = np.nancumsum(periods)  # seconds from the first tick (ring not wrapped at 50 Hz for 20 min)
    overruns = int(late.size)
    drives_on = [s["position"] for s in emulator.get("slaves", []) if s.get("state") == "OPERATION_ENABLED"]
    gates_set = [s["position"] for s in emulator.get("slaves", []) if s.get("gate")]
    return {
        "minutes": minutes,
        "update_rate": manager.update_rate,
        "load": load_process.how if load_process else None,
        "realtime": summary.get("realtime"),
        "ticks": stats.ticks,
        "overruns": overruns,
        "loop_overruns": stats.overruns,
        "overrun_ticks": [{"tick": int(i), "at_s": round(float(since_start[i]) + loop_began_s, 2),
                           "cost_ms": round(float(stats.costs[i]) * 1e3, 2),
                           "period_ms": round(float(periods[i]) * 1e3, 2)} for i in late[:50]],
        "tick_us": summary["tick_us"],
        "tick_cpu_us": summary["tick_cpu_us"],
        "worst_tick_us": summary["tick_us"]["max"],
        "jitter_us": {f"p{p:g}": round(v, 1) for p, v in jitter.items()} if jitter else {},
        "modes_visited": sorted(set(manager.modes_visited)),
        "injections": [i.as_dict() for i in injector.injections],
        "injected": len(injector.injections),
        # one pass asked for: the faults it ended without (the run's length ran out first)
        "not_injected": [f.name for f in FAULTS if f.name not in injected] if faults_once else [],
        "as_designed": sum(1 for i in injector.injections if i.outcome == i.fault.expect),
        "injector_error": injector.error,
        "unexpected_faults": unexpected,
        "counters": counters,
        "end": summary["end"],
        "gate_reset_failures": summary["gate_reset_failures"],
        "gates_left_set": gates_set,
        "drives_left_enabled": drives_on,
        "problems_at_end": [p for p in summary["problems"] if "at the end" in p or p.startswith("gate")],
        # every flag of the run with its words, when it went up and down: what a fault judged wrong is read back from
        "flags": summary["faults"],
    }

