"""The soak: the emulated robot for minutes at its control rate, cycling through all five modes with a remote
stream, while both cores are loaded and faults are injected on both buses.

It runs in-process (inside the emulation's private network namespace, as ``prime bringup --emulate`` does),
on the run path of ``prime bringup``: real-time loop, impedance manager, gate reset on the way out. A
helper thread (``Injector``) injects one fault every ``fault_every_s`` through the virtual Prime's control socket,
in turn from ``FAULTS`` (``soak_faults.py``: each says what the stack must do about it), and gives the operator's
reset for a latched one once the ring is whole (``Operator``).

Each injection is judged from the run's own fault history (the summary's), and every ERROR flag that no
injection explains (a drive fault nobody injected above all) is reported as unexpected (``soak_judge.py``). The
REMOTE stream publishes one MIT command per tick on the remote topic, the path the DDS bridge feeds.
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
from typing import TYPE_CHECKING, TypedDict

import numpy as np

from humanoid_prime.bench.soak_faults import FAULTS, SETTLE_S, Fault
from humanoid_prime.bench.soak_judge import Injection, InjectionDict, explained, judge
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.report import RunEnd
from humanoid_prime.runtime.run import run_loop
from humanoid_prime.runtime.session import (
    BringupOptions,
    Session,
    claim_control_socket,
    open_session,
    plan_session,
)
from humanoid_prime.virtual.ring.control import RingControl

if TYPE_CHECKING:
    from humanoid_prime.virtual.harness import EmulatorRecord

# the demonstration's order: every mode is entered from one whose pose is near its own
MODE_CYCLE = (Mode.ZERO_TORQUE, Mode.DAMPING, Mode.STANDBY, Mode.LOCOMOTION, Mode.REMOTE, Mode.STANDBY, Mode.DAMPING)
RESET_APPLIED_S = 2.0  # the longest an operator's reset may wait for the loop's next tick


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


class Operator:
    """The operator's fault resets: a latched fault is reset once it is flagged and its ring whole again (its
    drives' settings back), as a person at the robot would; one whose ring was whole only after its settle time is
    owed its reset (``owed``), given at the next ``pay_owed`` once the ring is whole. ``resets`` lists when each
    was sent, in seconds since the run began."""

    def __init__(self, control: RingControl, session: Session, stop: threading.Event) -> None:
        self.control, self.session, self.stop = control, session, stop
        self.resets: list[float] = []
        self.owed: list[Injection] = []  # latched faults not reset within their settle time: reset when whole

    def now(self) -> float:
        """Seconds since the run began."""
        return time.monotonic() - self.session.plan.began

    def owes(self, bus: str) -> bool:
        """A latched fault on ``bus`` still waits for its reset: nothing more goes onto it meanwhile."""
        return any(owed.fault.bus == bus for owed in self.owed)

    def reset_when_flagged(self, injection: Injection) -> None:
        """The reset once the fault is flagged and the ring whole, within the fault's settle time; owed otherwise."""
        deadline = time.monotonic() + injection.fault.settle_s
        while time.monotonic() < deadline and not self.stop.is_set():
            if self._whole(injection.fault) and self._flagged(injection):
                self._reset(injection)
                return
            time.sleep(0.02)
        self.owed.append(injection)

    def pay_owed(self) -> None:
        """A latched fault whose ring took longer than its settle time to be whole (a returning slave's clock
        relocking on a loaded machine) gets its reset once the ring is whole, as an operator would give it; one
        whose flag another reset has cleared meanwhile is owed nothing."""
        for injection in list(self.owed):
            if not self._flagged(injection, still=True):
                self.owed.remove(injection)
            elif self._whole(injection.fault):
                self.owed.remove(injection)
                self._reset(injection)

    def _whole(self, fault: Fault) -> bool:
        """The operator resets once the ring is whole and its drives' settings are back."""
        ethercat = self.session.ethercat
        if fault.bus != "ethercat" or ethercat is None or ethercat.master is None:
            return True
        return bool(ethercat.master.slave_ok.all()) and not ethercat.restore_pending()

    def _flagged(self, injection: Injection, still: bool = False) -> bool:
        pattern = injection.fault.flag
        return pattern is not None and any(
            fnmatch.fnmatch(r.key, pattern) and r.since_s >= injection.at_s and not (still and r.until_s is not None)
            for r in list(self.session.faults))

    def _reset(self, injection: Injection) -> None:
        """The operator's reset, and a wait until the loop has applied it: a fault injected meanwhile would be
        cleared by it, unseen."""
        manager = self.session.manager
        self.resets.append(self.now())
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


class Injector(threading.Thread):
    """One fault of ``faults`` every ``every_s`` in turn; ``operator`` resets the latched ones. With ``once``, one
    pass: after every fault has been injected once and the last has had its settle time, it ends the run
    (``stop``). No fault is injected that could not settle within ``run_s`` of the run's start, nor onto a bus
    that still waits for a latched fault's reset (a fault injected onto a drive still held would find its flag
    already up)."""

    def __init__(self, operator: Operator, every_s: float, run_s: float, *, once: bool = False,
                 faults: Sequence[Fault] = FAULTS) -> None:
        super().__init__(name="soak-faults", daemon=True)
        self.control, self.operator, self.every_s, self.once = operator.control, operator, every_s, once
        self.stop = operator.stop
        self.faults = tuple(faults)
        self.ends_s = operator.now() + run_s
        self.injections: list[Injection] = []
        self.error: str | None = None

    def run(self) -> None:
        operator, faults = self.operator, self.faults
        try:
            k = 0
            while not self.stop.wait(self.every_s):
                operator.pay_owed()
                if self.once and k == len(faults):
                    self.stop.wait(faults[-1].settle_s)
                    self.stop.set()
                    return
                fault = faults[k % len(faults)]
                if operator.owes(fault.bus):
                    continue  # its bus still waits for a latched fault's reset: the next fault goes onto a whole ring
                k += 1
                if operator.now() + fault.hold_s + fault.settle_s + 1.0 > self.ends_s:
                    return
                injection = Injection(fault, operator.now())
                self.injections.append(injection)
                result = fault.inject(self.control, operator.session)
                injection.detail = result if isinstance(result, str) else ""
                if fault.hold_s and self.stop.wait(fault.hold_s):
                    if fault.end is not None:
                        fault.end(self.control)
                    return
                if fault.end is not None:
                    fault.end(self.control)
                injection.done_s = operator.now()
                if fault.expect == "latched":
                    operator.reset_when_flagged(injection)
        except Exception as exc:  # a control call that failed ends the soak's injections, and says why
            self.error = f"{type(exc).__name__}: {exc}"


class OverrunTick(TypedDict):
    tick: int
    at_s: float  # since the run began
    cost_ms: float
    period_ms: float


class SoakFigures(TypedDict):
    """What ``bench_soak`` measured and found, as ``prime bench soak`` prints and judges it."""

    minutes: float
    update_rate: float
    load: str | None  # how the cores were loaded
    realtime: object  # what the loop could take of real-time scheduling (``runtime/realtime.py``)
    ticks: int
    overruns: int  # ticks that took, or periods that lasted, more than twice the period
    loop_overruns: int  # the loop's own count (``Rate``)
    overrun_ticks: list[OverrunTick]  # the first 50
    tick_us: dict[str, float | None]
    tick_cpu_us: dict[str, float | None]
    worst_tick_us: float | None
    jitter_us: dict[str, float]
    modes_visited: list[str]
    injections: list[InjectionDict]
    injected: int
    not_injected: list[str]  # one pass asked for: the faults it ended without (the run's length ran out first)
    as_designed: int
    injector_error: str | None
    unexpected_faults: list[dict[str, object]]
    counters: dict[str, int]
    end: RunEnd
    gate_reset_failures: list[str]
    gates_left_set: list[int]
    drives_left_enabled: list[int]
    problems_at_end: list[str]
    flags: list[dict[str, object]]  # every flag of the run, with its words, when it went up and down


def bench_soak(minutes: float = 10.0, *, rate: float | None = None, load: bool = True, cpu: int | None = None,
               fault_every_s: float = 6.0, dwell_s: float = 10.0, faults_once: bool = False,
               report: Callable[[str], None] = print, hardware_file: str | None = None) -> SoakFigures:
    """Run the soak (module docstring) in this process, which must be in a private network namespace. With
    ``faults_once`` it ends after one pass of every fault (``minutes`` is then the most it may take)."""
    from humanoid_prime.sim.demo import demo_stream
    from humanoid_prime.virtual.harness import attach_virtual_prime

    options = BringupOptions(emulated=True, duration=minutes * 60.0, update_rate=rate, realtime=True, cpu=cpu,
                             hardware_file=hardware_file, control_socket=None)
    stop = threading.Event()
    emulator: EmulatorRecord = {}
    load_process = None
    with contextlib.ExitStack() as stack:
        plan = plan_session(options)
        folder = stack.enter_context(tempfile.TemporaryDirectory(prefix="prime-soak-"))
        plan.options.control_socket = os.path.join(folder, "control.sock")
        claim_control_socket(plan, stack)
        virtual = attach_virtual_prime(stack, hardware_file=hardware_file, record=emulator, avoid_cpu=cpu)
        virtual.wire_into(options)
        session = open_session(plan, stack)
        manager = session.manager
        stream = demo_stream(session.robot, session.config, manager)
        if load:
            load_process = Load(os.cpu_count() or 2)
            stack.callback(load_process.close)
        operator = Operator(virtual.control, session, stop)
        injector = Injector(operator, fault_every_s, minutes * 60.0, once=faults_once)
        next_mode, mode_at = 0, 0.0

        def on_tick(m: ControllerManager) -> None:
            nonlocal next_mode, mode_at
            now = time.monotonic()
            if now >= mode_at:
                m.request_mode(MODE_CYCLE[next_mode % len(MODE_CYCLE)])
                next_mode += 1
                mode_at = now + dwell_s
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
                  operator.resets)
        stats = manager.stats
        ethercat, sito = session.ethercat, session.sito
        counters = {"ethercat_wkc_errors": ethercat.wkc_errors if ethercat is not None else 0,
                    "sito_send_failures": sito.send_failures if sito is not None else 0,
                    "stream_published": stream.published, "operator_resets": manager.resets}
    # after teardown: the end state, the gate reset
    injected = {i.fault.name for i in injections}
    unexpected = [r.as_dict() for r in session.faults
                  if r.level.name == "ERROR" and not explained(r, injections, session.faults)]
    k = min(stats.ticks, stats.capacity)
    periods = stats.periods[:k]
    jitter = stats.jitter_us((50, 99, 99.9, 100))
    # an overrun: a tick that took, or a period that lasted, more than twice the period
    late = np.flatnonzero((stats.costs[:k] > 2 * stats.period) | (periods > 2 * stats.period))
    since_start = np.nancumsum(periods)  # seconds from the first tick (ring not wrapped at 50 Hz for 20 min)
    slaves = emulator.get("slaves", [])  # as the drives had it at the end (``attach_virtual_prime``)
    tick_us = stats.tick_us()
    return {
        "minutes": minutes,
        "update_rate": manager.update_rate,
        "load": load_process.how if load_process else None,
        "realtime": session.reports.get("realtime"),
        "ticks": stats.ticks,
        "overruns": int(late.size),
        "loop_overruns": stats.overruns,
        "overrun_ticks": [{"tick": int(i), "at_s": round(float(since_start[i]) + loop_began_s, 2),
                           "cost_ms": round(float(stats.costs[i]) * 1e3, 2),
                           "period_ms": round(float(periods[i]) * 1e3, 2)} for i in late[:50]],
        "tick_us": tick_us,
        "tick_cpu_us": stats.split_us()["cpu"],
        "worst_tick_us": tick_us["max"],
        "jitter_us": {f"p{p:g}": round(v, 1) for p, v in jitter.items()} if jitter else {},
        "modes_visited": sorted(set(manager.modes_visited)),
        "injections": [i.as_dict() for i in injections],
        "injected": len(injections),
        "not_injected": [f.name for f in FAULTS if f.name not in injected] if faults_once else [],
        "as_designed": sum(1 for i in injections if i.outcome == i.fault.expect),
        "injector_error": injector.error,
        "unexpected_faults": unexpected,
        "counters": counters,
        "end": session.end,
        "gate_reset_failures": list(session.gate_reset_failures),
        "gates_left_set": [s["position"] for s in slaves if s.get("gate")],
        "drives_left_enabled": [s["position"] for s in slaves if s.get("state") == "OPERATION_ENABLED"],
        "problems_at_end": [p for p in session.problems if "at the end" in p or p.startswith("gate")],
        # what a fault judged wrong is read back from
        "flags": [r.as_dict() for r in session.faults],
    }
