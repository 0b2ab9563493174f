"""Ring supervision once every slave has reached OP: each pass reads every slave's AL state and acknowledges,
reconfigures or recovers the slaves that left OP, re-arming SYNC0 for each.

A pass runs every ``period_s`` (and at once when the cycle's working counter falls short while every slave was
in OP), so a slave that leaves OP is seen within one pass even when the working counter still looks right (a
slave that dropped to INIT but keeps counting, as one simulator does). The states come in one frame of our own
(``registers.py``), with the interpreter lock free while it travels. No pass runs while the cycle's frames get
no answer at all (the line cut before the first slave): it would learn nothing.

Reconfiguration. A slave back from a power cycle starts in INIT with its SyncManagers and FMMUs cleared. SOEM's
``ecx_reconfig_slave`` would bring it to SAFE-OP again, but waits for each state change inside one C call that
pysoem makes holding Python's interpreter lock: while the drive's firmware takes its time (up to SOEM's 2 s per
state) the control loop could not run. ``reconfigure`` takes the same steps one frame at a time: the SyncManager
and FMMU settings read back from the ESC at bring-up are written again, the mapping hook runs, and each state
change is polled. Then its clock is set to the ring's (``clocks.py``), SYNC0 armed and OP requested.
"""

from __future__ import annotations

import contextlib
import struct
import threading
import time
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np
import numpy.typing as npt

from humanoid_prime.control.rate import Rate
from humanoid_prime.drivers.ethercat.clocks import RingClocks
from humanoid_prime.drivers.ethercat.errors import SdoError
from humanoid_prime.drivers.ethercat.mapping import EscSetup
from humanoid_prime.drivers.ethercat.priority import HELPER_PRIORITY, feeding_priority
from humanoid_prime.drivers.ethercat.registers import NoReply, RingRegisters
from humanoid_prime.drivers.ethercat.states import change_timeout
from humanoid_prime.drivers.ethercat.wire import (
    AL_ERROR,
    AL_STATE_MASK,
    EEPROM_TO_PDI,
    REG_AL_CONTROL,
    REG_AL_STATUS,
    REG_EEPROM_CONFIG,
    AlState,
)

STATE_READS = 3  # AL-state reads in a pass while no slave answers them (their frames lost)
STATE_POLL_S = 0.001
_U16 = struct.Struct("<H")


class RingHealth(Protocol):
    """What the supervision keeps up to date, in ring order (the master's arrays)."""

    slave_ok: npt.NDArray[np.bool_]
    al_state: npt.NDArray[np.uint16]
    al_status_code: npt.NDArray[np.uint16]
    left_op: npt.NDArray[np.int64]
    left_op_code: npt.NDArray[np.uint16]
    health_version: int
    recovery_problems: dict[int, str]


class RingSupervisor:
    """Supervises the ring whose health is ``health``. ``remap(k)`` runs the PDO mapping hook on ring ``k`` (raises
    SdoError); ``recover(k)`` gives a slave that stopped answering its station address back (True when it answers
    there again); ``wkc()`` is the cycle's last working counter."""

    def __init__(self, health: RingHealth, registers: RingRegisters, clocks: RingClocks, setups: Sequence[EscSetup],
                 *, remap: Callable[[int], None], recover: Callable[[int], bool], wkc: Callable[[], int],
                 sync0_ns: int, period_s: float = 0.1, name: str = "ethercat-supervise",
                 clock: Callable[[], float] = time.monotonic, pause: Callable[[float], object] = time.sleep) -> None:
        self.health = health
        self.registers = registers
        self.clocks = clocks
        self.setups = list(setups)
        self.remap = remap
        self.recover = recover
        self.wkc = wkc
        self.sync0_ns = sync0_ns
        self.period_s = period_s
        self.name = name
        self.clock = clock  # times a returning slave's state changes; ``pause`` waits between looks (True: give up)
        self.pause = pause
        n = len(self.setups)
        self.lost = np.zeros(n, dtype=bool)  # slaves that answer no frame at all
        self.recoveries = 0
        self.state_rereads = 0  # state reads repeated because no reply came (their frame lost)
        self.passes = 0
        self.error: str | None = None  # the last exception a pass ran into
        self._clock_pending: set[int] = set()  # reconfigured slaves in SAFE-OP whose clock is not in step yet
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ---------------------------------------------------------------------------------------------- thread
    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    @property
    def stopping(self) -> threading.Event:
        return self._stop

    def wake(self) -> None:
        """The cycle's frames came back with a working counter short: look now (only while every slave was in
        OP; with one out, every cycle mismatches and says nothing new)."""
        self._wake.set()

    def _run(self) -> None:
        with feeding_priority(HELPER_PRIORITY):
            self._supervise()

    def _supervise(self) -> None:
        rate = Rate(1.0 / self.period_s, sleep=self._pause)
        while not self._stop.is_set():
            rate.wait()
            if self._stop.is_set():
                return
            self._wake.clear()
            if self.wkc() > 0:
                try:
                    self.check_once()
                except Exception as exc:  # the cycle must survive whatever recovery runs into
                    self.error = f"{type(exc).__name__}: {exc}"

    def _pause(self, seconds: float) -> bool:
        """A working-counter mismatch ends the wait only while every slave was in OP: passes back to back
        while one recovers would take frames the returning slave's clock needs to lock."""
        if self.health.slave_ok.all():
            return self._wake.wait(seconds) or self._stop.is_set()
        return self._stop.wait(seconds)

    # ------------------------------------------------------------------------------------------------ pass
    def check_once(self) -> None:
        """One pass: read every slave's AL state, record it, then move each slave out of OP one step back.

        The states are read again only after a read that no reply came for (its frame lost, or a ring or host that
        stalled past the frame's time): it says nothing. A slave that did not answer a read that came back is not
        answering. After ``STATE_READS`` reads with no reply every slave counts as not answering. The health
        arrays record what every slave reported before any request is written."""
        self.passes += 1
        states = None
        for _ in range(STATE_READS):
            states = self.registers.states()
            if states is not None:
                break
            self.state_rereads += 1
        n = len(self.setups)
        reported = states if states is not None else [None] * n
        self._record(reported)
        for k, reported_state in enumerate(reported):
            state = 0 if reported_state is None else reported_state[0]
            if state == AlState.OP:
                self.lost[k] = False
            elif state == AlState.SAFE_OP and k in self._clock_pending:
                self._start_clock(k)
            elif state in (AlState.SAFE_OP, AlState.SAFE_OP | AL_ERROR):
                self._push_toward_op(k, state)
            elif state:
                self.lost[k] = False
                self._reconfigure(k)
            else:
                self.lost[k] = not self.recover(k)

    def _record(self, reported: Sequence[tuple[int, int] | None]) -> None:
        health, changed = self.health, False
        for k, reported_state in enumerate(reported):
            state, code = (0, int(health.al_status_code[k])) if reported_state is None else reported_state
            if (bool(health.slave_ok[k]), int(health.al_state[k]), int(health.al_status_code[k])) != (
                    state == AlState.OP, state, code):
                if health.slave_ok[k] and state != AlState.OP:
                    health.left_op[k] += 1
                    health.left_op_code[k] = code if state & AL_ERROR else 0  # a code counts with its error
                health.slave_ok[k] = state == AlState.OP
                health.al_state[k] = state
                health.al_status_code[k] = code
                changed = True
        if changed:
            health.health_version += 1

    def _push_toward_op(self, k: int, state: int) -> None:
        """Acknowledge an error in SAFE-OP, else request OP."""
        with contextlib.suppress(NoReply):  # the next pass looks again
            self.registers.request_state(k, AlState.SAFE_OP | AL_ERROR if state & AL_ERROR else AlState.OP)

    # ------------------------------------------------------------------------------------- reconfiguration
    def reconfigure(self, k: int) -> int:
        """SOEM's ``ecx_reconfig_slave`` one frame at a time: INIT (with an error acknowledge, as
        ``ecx_config_init`` sends it), the SyncManagers, PRE-OP, the mapping hook, SAFE-OP, the FMMUs. Returns the
        state reached (0 when a frame went unanswered). A slave that refuses a state (its error flag) is not waited
        out: the next pass takes it from there. The EEPROM goes to the drive's PDI before INIT is awaited, as in
        SOEM's function."""
        registers, setup = self.registers, self.setups[k]
        try:
            registers.request_state(k, AlState.INIT | AL_ERROR)
            registers.write(k, REG_EEPROM_CONFIG, bytes((EEPROM_TO_PDI,)))
            state = self._await_state(k, AlState.INIT)
            if state != AlState.INIT:
                return state
            for address, data in setup.sync_managers:
                registers.write(k, address, data)
            registers.request_state(k, AlState.PRE_OP)
            state = self._await_state(k, AlState.PRE_OP)
            if state != AlState.PRE_OP:
                return state
            try:
                self.remap(k)
            except SdoError:  # it stays in PRE-OP (flagged, "in PRE-OP") and the next pass tries again
                return state
            registers.request_state(k, AlState.SAFE_OP)
            state = self._await_state(k, AlState.SAFE_OP)
            for address, data in setup.fmmus:
                registers.write(k, address, data)
            return state
        except NoReply:
            return 0

    def _await_state(self, k: int, wanted: int) -> int:
        """Poll slave ``k``'s AL status until it shows ``wanted``, refuses (error flag), the wait runs out or the
        master closes; returns the state (without the error flag)."""
        deadline = self.clock() + change_timeout(wanted)[0]
        while True:
            try:
                status: int = _U16.unpack(self.registers.read(k, REG_AL_STATUS, 2))[0]
            except NoReply:
                status = 0
            state = status & AL_STATE_MASK
            if state == wanted or status & AL_ERROR or self.clock() > deadline or self.pause(STATE_POLL_S):
                return state

    def _reconfigure(self, k: int) -> None:
        if self.reconfigure(k) == AlState.SAFE_OP:
            self._clock_pending.add(k)
            self._start_clock(k)

    def _start_clock(self, k: int) -> None:
        """Ring ``k``, reconfigured and in SAFE-OP: its clock back in step with the ring's, then SYNC0 armed on it
        and OP requested. A clock that does not come into step keeps the slave in SAFE-OP, said in
        ``recovery_problems``, and the next pass tries again."""
        health = self.health
        problem = self.clocks.set_clock(k, self._kept_clock)
        if problem is None:
            try:
                self.clocks.arm_sync0(k, self.sync0_ns)
                self.registers.write(k, REG_AL_CONTROL, _U16.pack(AlState.OP))
            except NoReply as exc:
                problem = f"SYNC0 could not be armed ({exc.what})"
        if problem is not None:
            if health.recovery_problems.get(k) != problem:
                health.recovery_problems[k] = problem
                health.health_version += 1
            return
        self._clock_pending.discard(k)
        if health.recovery_problems.pop(k, None) is not None:
            health.health_version += 1
        self.recoveries += 1

    def _kept_clock(self, j: int) -> bool:
        kept = int(self.health.al_state[j]) & AL_STATE_MASK in (AlState.SAFE_OP, AlState.OP)
        return kept and j not in self._clock_pending
