"""The EtherCAT master on a raw NIC: SOEM through pysoem, owning the cycle in-process (DESIGN §3).

Bring-up: ``config_init`` enumerates the ring and leaves it in PRE-OP; the PRE-OP -> SAFE-OP hook maps
the PDOs of ``drivers/erob/objects.py`` over SDO (0x1C12/0x1C13 cleared, 0x1600/0x1A00 written, assignment
restored); ``config_map`` then reads the mapping back and lays out the IO map; ``config_dc`` measures the
ring and SYNC0 is activated on every slave. Only after that, with no mailbox traffic left, are the
slaves asked for SAFE-OP and then OP, while the base class's fast loop keeps their outputs fed.

Threads. The controller manager's thread runs the cycle (``send``/``receive``). SDO transfers run in
the caller's thread, one in flight per slave (one per ring when ``parallel_sdo`` is off). This relies on
SOEM's frame layer, which gives every datagram its own buffer index under its own mutexes, so mailbox
frames and process-data frames interleave without either waiting for the other; pysoem releases the GIL
for the duration of each transfer and of each cycle receive. Only SOEM's error list is shared: an abort
raised by another slave's transfer may be popped in the wrong thread, so such errors are handed to their
owner and the transfer that popped them is retried. Emergencies (EMCY) are routed by slave, never raised.
On the emulated ring a gain switch (20 writes over 10 slaves) takes about 6 ms this way against about 20 ms
one transfer at a time (``bench/ethercat.py``); on a small machine a frame now and then comes back after its
2 ms timeout, and such a transfer is repeated.

SOEM's socket. SOEM polls its socket for each frame it waits for ("non blocking call to retrieve frame from
socket", oshw/linux/nicdrv.c) but opens it blocking with a 1 µs receive timeout, which the kernel rounds up to
whole scheduler ticks. Blocking, a lost frame holds its thread for those ticks (6.4 ms measured) instead of the
2 ms frame timeout, and a thread whose frame another thread has already filed takes the receive lock and sleeps in
``recv`` until some other frame arrives: the last transfer of a parallel gain switch, or the loop's own receive
while transfers run, waits for a frame that is already there. ``poll_frames`` makes the socket non-blocking, so
each waiting thread polls until its frame is filed or its timeout passes. It is for the time a real-time thread
owns the cycle: the bring-up loop, the drives' enabling and the keeper run at normal priority, and polling there
put a loaded machine's bring-up behind its other work until a slave missed its DC lock. Nor does the master poll
where the kernel delivers the NIC's frames from a thread (``threaded_receive``): a real-time thread polling on that
thread's CPU would keep it, below the loop's priority, from delivering the very frame it waits for.
A supervision thread, woken by a working-counter mismatch, reads the AL states and acknowledges,
reconfigures or recovers slaves that left OP, re-arming SYNC0 for each.

Reconfiguration. A slave back from a power cycle starts in INIT with its SyncManagers and FMMUs cleared. SOEM's
``ecx_reconfig_slave`` brings it to SAFE-OP again, but waits for each state change inside one C call, and pysoem
holds Python's interpreter lock through it: while the drive's firmware takes its time (up to SOEM's 2 s per state),
the control loop cannot run, and every other drive's output watchdog runs out. ``_reconfigure`` takes the same steps
from Python instead, one frame per call: the SyncManager and FMMU settings read back from each ESC at bring-up are
written again, the mapping hook runs with its transfers outside the lock, and each state change is polled with the
lock free in between.
"""

from __future__ import annotations

import os
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pysoem

from humanoid_prime.control.rate import Rate
from humanoid_prime.drivers.erob.objects import (
    MAPPING_WRITES,
    RATED_TORQUE,
    RXPDO_STRUCT,
    TXPDO_STRUCT,
)
from humanoid_prime.drivers.ethercat.master import (
    AL_ERROR,
    AL_INIT,
    AL_OP,
    AL_PRE_OP,
    AL_SAFE_OP,
    RX_DTYPE,
    TX_DTYPE,
    EthercatMaster,
    RingError,
    SdoError,
    SlaveInfo,
    describe_states,
)

STATE_TIMEOUT_US = 3_000_000  # PRE-OP and SAFE-OP transitions (blocking, before the cycle starts)
TRANSFER_ATTEMPTS = 4  # one SDO transfer, when frames get lost or another slave's error was popped
STATE_READS = 3  # AL-state reads in a pass, while no slave answers them (their frames lost)
# A returning slave's state changes, as SOEM's ecx_statecheck waits for them (EC_TIMEOUTSTATE, 2 s, polled each ms)
STATE_CHANGE_TIMEOUT_S = 2.0
STATE_POLL_S = 0.001

# ESC registers (ETG.1000.4): AL control and status, EEPROM owner, the FMMUs (16 bytes each) and SyncManagers
REG_AL_CONTROL = 0x0120
REG_AL_STATUS = 0x0130
REG_EEPROM_CONFIG = 0x0500
EEPROM_TO_PDI = b"\x01"
REG_FMMU = 0x0600
REG_SM = 0x0800
REG_FMMU_SM_COUNT = 0x0004  # u8 FMMUs, u8 SyncManagers the ESC has
SOEM_MAXSM, SOEM_MAXFMMU = 8, 4  # what SOEM configures at most (EC_MAXSM, EC_MAXFMMU in ethercatmain.h)
SM_REPEAT = 0x02  # SyncManager activate bit 1: the mailbox repeat request, which SOEM toggles; a fresh ESC has it clear
# Distributed clock (ETG.1000.4): ESC features bit 2 = DC (SOEM's hasdc), the system time, its offset (u64) and the
# propagation delay (u32) after it, the difference to the reference clock's time the frames bring (0x092C: received
# minus local in bits 0-30, bit 31 set when the local copy is the smaller), the speed counter start (0x0930: a write
# resets the difference's filter, ESC datasheet section I 9.1.3.6)
REG_ESC_FEATURES = 0x0008
ESC_FEATURE_DC = 0x04
REG_DC_SYSTEM_TIME = 0x0910
REG_DC_OFFSET = 0x0920
REG_DC_DELAY = 0x0928
REG_DC_DIFFERENCE = 0x092C
REG_DC_SPEED_START = 0x0930
DC_LOCAL_SMALLER = 0x80000000
DC_DIFFERENCE_SATURATED = 0x7FFFFFFF
DC_STEP_NS = 1_000_000  # a clock further off than this gets a new offset at once (IgH's EC_SYSTEM_TIME_TOLERANCE_NS)
DC_SYNC_WINDOW_NS = 10_000  # in step with the ring (IgH waits for this before starting SYNC0: EC_DC_MAX_SYNC_DIFF_NS)
DC_FILTER_FRAMES = 16  # time distributions to let through after a filter reset before the difference is read
DC_CORRECTIONS = 4  # offset corrections by the measured difference before a clock counts as not coming into step
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_CLOCK = struct.Struct("<QQQ")  # 0x0910 system time, 0x0918 receive time, 0x0920 offset: read in one datagram
_OFFSET_DELAY = struct.Struct("<QI")  # 0x0920 offset and 0x0928 delay: written in one datagram, as IgH does


@dataclass(frozen=True)
class EscSetup:
    """A slave's SyncManager and FMMU registers as SOEM programmed them at bring-up: (address, bytes) each, in the
    order ``ecx_reconfig_slave`` writes them. Only SOEM's own fields: the SyncManager's status and PDI-control bytes,
    which the ESC sets, go back as 0, as SOEM writes them, and its activate byte without a mailbox repeat request."""

    sync_managers: tuple[tuple[int, bytes], ...]
    fmmus: tuple[tuple[int, bytes], ...]
    dc: bool = False  # the ESC has a distributed clock
    dc_delay: int = 0  # its propagation delay from the reference clock (0x0928), as ``config_dc`` measured it


class SoemMaster(EthercatMaster):
    """pysoem on the NIC named in ``prime_hardware.yaml`` (``buses.ethercat.interface``)."""

    supervise_period_s = 0.1  # how often a ring with a slave out of OP is checked again

    def __init__(self, interface: str, *, update_rate: float, bringup_rate: float = 1000.0,
                 sync0_period_s: float | None = None, unsafe_sync0_period_s: float | None = None,
                 bringup_timeout_s: float = 30.0, parallel_sdo: bool = True, sdo_in_flight: int | None = None,
                 sdo_timeout_s: float = 0.7, frame_timeout_us: int = 2000,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(interface, update_rate=update_rate, bringup_rate=bringup_rate,
                         sync0_period_s=sync0_period_s, unsafe_sync0_period_s=unsafe_sync0_period_s,
                         bringup_timeout_s=bringup_timeout_s)
        self.parallel_sdo = parallel_sdo
        # transfers in flight at once over the ring: one per slave unless capped (or 1 when not parallel)
        self.sdo_in_flight = (sdo_in_flight or 64) if parallel_sdo else 1
        self._in_flight_slots = threading.BoundedSemaphore(self.sdo_in_flight)
        self.sdo_timeout_us = round(sdo_timeout_s * 1e6)
        self.frame_timeout_us = frame_timeout_us
        self._register_timeout_us = round(frame_timeout_us * 3)  # one register frame, or a recovery's frames
        self._clock = clock  # tells a lost frame (early) from a mailbox timeout (late)
        self.emergencies: dict[int, int] = {}  # ring position -> last EMCY error code
        self.recoveries = 0
        self.lost_frames = 0  # SDO transfers repeated because a frame of the exchange did not come back
        self.state_rereads = 0  # AL-state reads repeated because no slave answered one (its frame lost)
        self.threaded_receive: str | None = None  # why the NIC's frames arrive through a kernel thread, if they do
        self._socket: int | None = None  # SOEM's socket, where it could be told from this process's others
        self.supervision_error: str | None = None  # the last exception a recovery attempt ran into
        self._m: pysoem.Master | None = None
        self._pslaves: list = []
        self._locks: list[threading.RLock] = []
        self._stray: dict[int, Exception] = {}
        self._stray_lock = threading.Lock()
        self._hook_errors: dict[int, str] = {}
        self._esc_setups: list[EscSetup] = []
        self._dc_reference: int | None = None  # ring position of the reference clock: SOEM's first slave with DC
        self._clock_pending: set[int] = set()  # reconfigured slaves in SAFE-OP whose clock is not in step yet
        self._lost = np.zeros(0, dtype=bool)
        self._check = threading.Event()
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._out_buf = bytearray()
        self._in_buf = bytearray()
        self._out_pairs: list[tuple[object, memoryview]] = []  # (pysoem slave, its 13 output bytes)
        self._in_pairs: list[tuple[object, slice]] = []  # (pysoem slave, where its 15 input bytes go)

    # ---------------------------------------------------------------------------- discovery
    def _discover(self) -> Sequence[SlaveInfo]:
        try:
            socket.if_nametoindex(self.interface)
        except OSError:
            raise RingError(f"no network interface {self.interface!r} (buses.ethercat.interface in "
                            "prime_hardware.yaml); list them with `ip link` or pass --interface") from None
        m = pysoem.Master()
        theirs = packet_sockets(self.interface)
        try:
            m.open(self.interface)
        except ConnectionError:
            raise RingError(f"cannot open {self.interface!r} for EtherCAT: SOEM needs a raw socket, so run as root "
                            "or grant CAP_NET_RAW") from None
        self._m = m
        opened = packet_sockets(self.interface) - theirs
        self._socket = opened.pop() if len(opened) == 1 else None  # SOEM opens one per port
        self.threaded_receive = threaded_receive(self.interface)
        m.sdo_read_timeout = self.sdo_timeout_us
        m.sdo_write_timeout = self.sdo_timeout_us
        if m.config_init() <= 0:
            self._close()
            raise RingError(f"no EtherCAT slave answered on {self.interface}: check the cable and the drives' power, "
                            "and that no other master (IgH) owns this NIC")
        self._pslaves = list(m.slaves)
        n = len(self._pslaves)
        # re-entrant: reconfig holds a slave's lock while SOEM calls the mapping hook, which transfers under it
        self._locks = [threading.RLock() for _ in range(n)] if self.parallel_sdo else [threading.RLock()] * n
        self._lost = np.zeros(n, dtype=bool)
        for slave in self._pslaves:
            slave.add_emergency_callback(self._on_emergency)
        reached = m.state_check(pysoem.PREOP_STATE, STATE_TIMEOUT_US)
        m.read_state()
        found = [SlaveInfo(k, s.name, s.man, s.id, s.rev, s.state, s.al_status) for k, s in enumerate(self._pslaves)]
        if reached != pysoem.PREOP_STATE:
            self._close()
            raise RingError(f"EtherCAT ring on {self.interface} did not reach PRE-OP: "
                            f"{describe_states(found, AL_PRE_OP)}")
        return found

    # -------------------------------------------------------------------------- configuration
    def _map_pdos(self, k: int, release_gil: bool = False) -> None:
        """PRE-OP -> SAFE-OP hook (SOEM calls it from config_map, ``_reconfigure`` with ``release_gil``): write
        the PDO mapping, each write with the runtime SDOs' bounded retry, then read the drive's rated torque
        (0x6076).

        A drive powers up with ZeroErr's own mapping (``POWER_UP_RXPDO``), so these writes always change it.
        """
        slave = self._pslaves[k]
        try:
            for index, sub_index, data in MAPPING_WRITES:
                self._transfer(k, index, sub_index, lambda i=index, s=sub_index, d=data:
                               slave.sdo_write(i, s, d, release_gil=release_gil))
        except SdoError as exc:
            verdict = "the drive refused it" if exc.abort_code is not None else "the drive did not answer"
            self._hook_errors[k] = (f"ring {k}: PDO mapping write 0x{exc.index:04X}:{exc.sub_index:02X}: "
                                    f"{exc.problem} ({verdict})")
            raise
        self._hook_errors.pop(k, None)
        self._read_rated_torque(k, release_gil)

    def _read_rated_torque(self, k: int, release_gil: bool = False) -> None:
        """0x6076 of ring ``k`` into ``rated_torque_nm`` (u32 mN*m); an unreadable one is left NaN and said why."""
        slave = self._pslaves[k]
        try:
            raw = self._transfer(k, RATED_TORQUE, 0, lambda: slave.sdo_read(RATED_TORQUE, 0, release_gil=release_gil))
        except SdoError as exc:
            self.rated_torque_problems[k] = exc.problem
            return
        self.store_rated_torque(k, raw)

    def _configure(self) -> None:
        m = self._require()
        n = len(self._pslaves)
        for slave in self._pslaves:
            slave.config_func = self._map_pdos
        m.manual_state_change = 1  # config_map must not ask for SAFE-OP before SYNC0 is set
        try:
            m.config_map()
        except pysoem.ConfigMapError as exc:
            problems = "; ".join(_describe(e) for e in exc.error_list)
            raise RingError(f"mapping the PDOs on {self.interface} failed: {problems}") from None
        except Exception as exc:
            problems = "; ".join(self._hook_errors.values()) or _describe(exc)
            raise RingError(f"mapping the PDOs on {self.interface} failed: {problems}") from None
        for k, slave in enumerate(self._pslaves):
            if (len(slave.output), len(slave.input)) != (RXPDO_STRUCT.size, TXPDO_STRUCT.size):
                raise RingError(f"ring {k} maps {len(slave.output)} output and {len(slave.input)} input bytes, "
                                f"expected {RXPDO_STRUCT.size} and {TXPDO_STRUCT.size} (drivers/erob/objects.py); "
                                "the drive did not accept the PDO mapping")
        if not m.config_dc():
            raise RingError(f"no slave on {self.interface} supports distributed clocks; eRob CSP needs DC "
                            "(CSP in free run faults the drives with 4616)")
        self._esc_setups = [self._read_esc_setup(k) for k in range(n)]
        self._dc_reference = next((k for k, setup in enumerate(self._esc_setups) if setup.dc), None)
        for slave in self._pslaves:
            slave.dc_sync(True, self.sync0_ns)
        m.state = pysoem.SAFEOP_STATE
        m.write_state()
        if m.state_check(pysoem.SAFEOP_STATE, STATE_TIMEOUT_US) != pysoem.SAFEOP_STATE:
            self._store_states(self._read_states())
            raise RingError(self._not_op_message("did not reach SAFE-OP", AL_SAFE_OP))
        self.expected_wkc = m.expected_wkc
        self._out_buf = bytearray(n * RX_DTYPE.itemsize)
        self._in_buf = bytearray(n * TX_DTYPE.itemsize)
        self.outputs = np.frombuffer(self._out_buf, dtype=RX_DTYPE)
        self.inputs = np.frombuffer(self._in_buf, dtype=TX_DTYPE)
        view = memoryview(self._out_buf)
        out_size, in_size = RX_DTYPE.itemsize, TX_DTYPE.itemsize
        self._out_pairs = [(s, view[k * out_size:(k + 1) * out_size]) for k, s in enumerate(self._pslaves)]
        self._in_pairs = [(s, slice(k * in_size, (k + 1) * in_size)) for k, s in enumerate(self._pslaves)]

    def _request_op(self) -> None:
        m = self._require()
        m.state = pysoem.OP_STATE
        m.write_state()

    def _read_states(self) -> list[tuple[int, int]]:
        self._require().read_state()
        return [(s.state, s.al_status) for s in self._pslaves]

    def _advance(self, slaves: Sequence[tuple[int, int]]) -> None:
        for k, state in slaves:
            _push_toward_op(self._pslaves[k], state)

    def _started(self) -> None:
        self._stop.clear()
        self._supervisor = threading.Thread(target=self._supervise, name=f"ethercat-supervise-{self.interface}",
                                            daemon=True)
        self._supervisor.start()

    def poll_frames(self, poll: bool) -> bool:
        if self._socket is None or self._m is None or (poll and self.threaded_receive is not None):
            return False
        os.set_blocking(self._socket, not poll)
        return poll

    # -------------------------------------------------------------------------------- cyclic
    def _send(self) -> None:
        for slave, view in self._out_pairs:
            slave.output = bytes(view)
        self._m.send_processdata()

    def _receive(self) -> int:
        wkc = self._m.receive_processdata(self.frame_timeout_us, release_gil=True)
        buf = self._in_buf
        for slave, where in self._in_pairs:
            buf[where] = slave.input
        return wkc

    def _wkc_mismatch(self) -> None:
        # A frame that did not come back at all (lost, or late past its timeout) says nothing about the slaves,
        # and a state read now would be lost the same way: pysoem's state calls hold the GIL while SOEM waits
        # out their timeouts, stalling the cycle. The supervision looks once frames return with a wrong count.
        if self.wkc > 0:
            self._check.set()

    # ---------------------------------------------------------------------------- supervision
    def _supervise(self) -> None:
        """Check the ring every ``supervise_period_s`` while a slave is out of OP, and at once when the cycle
        sees a working-counter mismatch while every slave was in OP (``_pause``). Not while the cycle's frames
        get no answer at all (the line cut before the first slave): pysoem's state reads and SOEM's recovery hold
        the interpreter lock while they wait out their timeouts, and would stall the cycle to learn nothing."""
        rate = Rate(1.0 / self.supervise_period_s, sleep=self._pause)
        while not self._stop.is_set():
            rate.wait()
            if self._stop.is_set():
                return
            woken = self._check.is_set()
            self._check.clear()
            if (woken or not self.slave_ok.all()) and self.wkc > 0:
                try:
                    self._check_ring()
                except Exception as exc:  # the cycle must survive whatever recovery runs into
                    self.supervision_error = _describe(exc)

    def _pause(self, seconds: float) -> bool:
        """The supervision's sleep: a working-counter mismatch ends it only while every slave was in OP. With one
        out, every cycle mismatches and says nothing new; passes back to back (hundreds a second at 1 kHz) would
        hold the interpreter lock in pysoem's state reads often enough that the loop's frames came too late for the
        returning slave's distributed clock ever to lock."""
        if self.slave_ok.all():
            return self._check.wait(seconds)
        return self._stop.wait(seconds)

    def _check_ring(self) -> None:
        """One pass of SOEM's state check: acknowledge, re-request OP, reconfigure or recover each slave.

        The states are read again only after a read that no slave answered: its frame was lost (a ring, or an
        emulated robot, that stalled past SOEM's timeout, or a supervision thread kept off the CPU that long), and
        it says nothing. A read that some slave answered came back, so a slave it has no state for did not answer
        at its address. A read costs two frames with the interpreter lock held; with a slave gone, three of them
        each pass held it for milliseconds at 1 kHz on the emulated robot. After ``STATE_READS`` lost reads every
        slave counts as not answering. The health arrays record what every slave reported before any request is
        written (a reference clock back from a power cycle is set to the time of a slave that this pass found in
        SAFE-OP or OP).
        """
        m = self._require()
        answered: dict[int, tuple[int, int]] = {}  # position -> (state, AL status code)
        for _ in range(STATE_READS):
            m.read_state()
            answered = {k: (slave.state, slave.al_status) for k, slave in enumerate(self._pslaves)
                        if slave.state != pysoem.NONE_STATE}
            if answered:
                break
            self.state_rereads += 1
        changed = False
        states = []
        for k, slave in enumerate(self._pslaves):
            state, code = answered.get(k, (pysoem.NONE_STATE, slave.al_status))
            states.append(state)
            if (bool(self.slave_ok[k]), int(self.al_state[k]), int(self.al_status_code[k])) != (
                    state == AL_OP, state, code):
                if self.slave_ok[k] and state != AL_OP:
                    self.left_op[k] += 1
                self.slave_ok[k] = state == AL_OP
                self.al_state[k] = state
                self.al_status_code[k] = code
                changed = True
        for k, (slave, state) in enumerate(zip(self._pslaves, states, strict=True)):
            if state == AL_OP:
                self._lost[k] = False
            elif state == AL_SAFE_OP and k in self._clock_pending:
                self._start_clock(k)
            elif not _push_toward_op(slave, state):
                if state > pysoem.NONE_STATE:
                    self._reconfigure(k)
                else:
                    self._lost[k] = True
                    if slave.recover(self._register_timeout_us) > 0:
                        self._lost[k] = False
        if changed:
            self.health_version += 1

    def _reconfigure(self, k: int) -> None:
        """A slave back in INIT or PRE-OP: SAFE-OP again (``_reconfig_slave``), then its clock, SYNC0 and OP."""
        with self._locks[k]:
            state = self._reconfig_slave(k)
        if state == AL_SAFE_OP:
            self._clock_pending.add(k)
            self._start_clock(k)

    def _start_clock(self, k: int) -> None:
        """Ring ``k``, reconfigured and in SAFE-OP: its clock back in step with the ring's (``_set_clock``), then
        SYNC0 armed on it and OP requested. A clock that does not come into step keeps the slave in SAFE-OP, said
        in ``recovery_problems``, and the next supervision pass tries again."""
        problem = self._set_clock(k)
        if problem is not None:
            if self.recovery_problems.get(k) != problem:
                self.recovery_problems[k] = problem
                self.health_version += 1
            return
        self._clock_pending.discard(k)
        if self.recovery_problems.pop(k, None) is not None:
            self.health_version += 1
        slave = self._pslaves[k]
        slave.dc_sync(True, self.sync0_ns)
        slave.state = pysoem.OP_STATE
        slave.write_state()
        self.recoveries += 1

    def _set_clock(self, k: int) -> str | None:
        """Bring ring ``k``'s system time back onto the ring's; None once it is within ``DC_SYNC_WINDOW_NS``, else
        why not.

        A power cycle clears a slave's offset (0x0920) and delay (0x0928) and starts its local clock from 0, and
        neither SOEM's reconfiguration nor its recovery sets them again: SYNC0 would then run on a clock years off
        the ring's, out of step with the frames. As IgH's master does for a slave it finds reset, a clock more than
        ``DC_STEP_NS`` off gets a new offset at once, written with the delay measured at bring-up; the time it is
        compared with is another clock's, read in the next frame (the reference clock's, or for the reference
        clock itself that of the first slave that kept its own). Then the difference the ESC measures against the
        time distribution (0x092C) is read, after a filter reset and ``DC_FILTER_FRAMES`` cycles, and taken off
        the offset until it is within ``DC_SYNC_WINDOW_NS``, at most ``DC_CORRECTIONS`` times."""
        setup = self._esc_setups[k]
        reference = self._dc_reference
        if not setup.dc or reference is None:
            return None
        if k == reference:  # compared with, and measured by, a slave that kept its clock: not one reconfigured
            kept = next((j for j in range(len(self._pslaves)) if j != k and self._esc_setups[j].dc
                         and j not in self._clock_pending and self.al_state[j] & 0x0F in (AL_SAFE_OP, AL_OP)), None)
            if kept is None:
                return None  # every clock started again: the others are set to this one's
            other, measured, sign = kept, kept, -1
        else:
            other, measured, sign = reference, k, 1
        slave, timeout = self._pslaves[k], self._register_timeout_us
        source = self._pslaves[other]
        try:
            own, _received, offset = _CLOCK.unpack(slave._fprd(REG_DC_SYSTEM_TIME, _CLOCK.size, timeout))
            step = _signed64(_U64.unpack(source._fprd(REG_DC_SYSTEM_TIME, 8, timeout))[0] - own)
            if abs(step) > DC_STEP_NS:
                offset = (offset + step) & 0xFFFFFFFFFFFFFFFF
                slave._fpwr(REG_DC_OFFSET, _OFFSET_DELAY.pack(offset, setup.dc_delay), timeout)
            before = None
            for _ in range(DC_CORRECTIONS + 1):
                difference = self._clock_difference(measured)
                if difference is None:
                    return "its clock could not be compared with the ring's: no time distribution reached it"
                difference *= sign
                if abs(difference) <= DC_SYNC_WINDOW_NS:
                    return None
                if before is not None and abs(difference) > abs(before):
                    # the correction made it worse: this ESC reads bit 31 the other way round (ESC documents
                    # disagree on it), so the last correction goes back and this one the other way
                    sign, difference = -sign, -difference
                before = difference
                offset = (offset + difference) & 0xFFFFFFFFFFFFFFFF
                slave._fpwr(REG_DC_OFFSET, _U64.pack(offset), timeout)
        except pysoem.WkcError:
            return "its clock registers did not answer"
        return (f"its clock did not come into step with the ring's: {difference} ns off after {DC_CORRECTIONS} "
                f"corrections (SYNC0 needs it within {DC_SYNC_WINDOW_NS} ns)")

    def _clock_difference(self, k: int) -> int | None:
        """Ring ``k``'s 0x092C as signed ns (the reference clock's time minus its own) over the time distributions
        of ``DC_FILTER_FRAMES`` cycles after a filter reset; None when the cycle brought none in time."""
        slave, timeout = self._pslaves[k], self._register_timeout_us
        slave._fpwr(REG_DC_SPEED_START, slave._fprd(REG_DC_SPEED_START, 2, timeout), timeout)
        if not self._await_cycles(DC_FILTER_FRAMES):
            return None
        raw = _U32.unpack(slave._fprd(REG_DC_DIFFERENCE, 4, timeout))[0]
        magnitude = raw & DC_DIFFERENCE_SATURATED
        return magnitude if raw & DC_LOCAL_SMALLER else -magnitude

    def _await_cycles(self, count: int) -> bool:
        """Wait until the cycle has brought the reference clock's time ``count`` times (SOEM's ``DCtime`` changed),
        polled with the lock free; False if that took more than four times as long as it should, or the master
        closes."""
        m = self._require()
        deadline = time.monotonic() + 4 * count * self.cycle_ns / 1e9 + 1.0
        seen, last = 0, m.dc_time
        while seen < count:
            if time.monotonic() > deadline or self._stop.wait(STATE_POLL_S):
                return False
            now = m.dc_time
            if now != last:
                seen, last = seen + 1, now
        return True

    def _read_esc_setup(self, k: int) -> EscSetup:
        """Ring ``k``'s SyncManagers (those with a start address, as SOEM writes them), FMMUs (those SOEM set) and
        distributed clock: whether it has one and its propagation delay, read after ``config_dc``."""
        slave = self._pslaves[k]
        try:
            fmmu_count, sm_count = slave._fprd(REG_FMMU_SM_COUNT, 2)
            sms = slave._fprd(REG_SM, 8 * min(sm_count, SOEM_MAXSM))
            fmmus = slave._fprd(REG_FMMU, 16 * min(fmmu_count, SOEM_MAXFMMU))
            dc = bool(_U16.unpack(slave._fprd(REG_ESC_FEATURES, 2))[0] & ESC_FEATURE_DC)
            delay = _U32.unpack(slave._fprd(REG_DC_DELAY, 4))[0] if dc else 0
        except pysoem.WkcError:
            raise RingError(f"ring {k}: its SyncManager, FMMU and clock registers could not be read back (no reply), "
                            "so it could not be reconfigured after a power cycle") from None
        sync_managers = tuple((REG_SM + 8 * n, sms[8 * n:8 * n + 5] + bytes((0, sms[8 * n + 6] & ~SM_REPEAT & 0xFF, 0)))
                              for n in range(len(sms) // 8) if _U16.unpack_from(sms, 8 * n)[0])
        return EscSetup(sync_managers=sync_managers,
                        fmmus=tuple((REG_FMMU + 16 * n, fmmus[16 * n:16 * n + 16])
                                    for n in range(len(fmmus) // 16) if any(fmmus[16 * n:16 * n + 16])),
                        dc=dc, dc_delay=delay)

    def _reconfig_slave(self, k: int) -> int:
        """SOEM's ``ecx_reconfig_slave`` (ethercatconfig.c) one frame at a time: INIT, the SyncManagers, PRE-OP,
        the mapping hook, SAFE-OP, the FMMUs. Returns the state reached (0 when a frame went unanswered). INIT goes
        with an error acknowledge, as SOEM's ``ecx_config_init`` sends it: a slave whose error flag stayed set would
        refuse PRE-OP.

        Each state change is polled with the interpreter lock free between reads, and a slave that refuses one
        (its AL status shows the error flag) is not waited out: the next supervision pass takes it from there.
        The EEPROM goes to the drive's PDI before INIT is awaited, as in SOEM's function and at bring-up. SOEM's
        cache then still says the master holds it; only a recovery from the next power cycle reads it again, and a
        power cycle gives it back to the master."""
        slave, setup = self._pslaves[k], self._esc_setups[k]
        timeout = self._register_timeout_us
        try:
            slave._fpwr(REG_AL_CONTROL, _U16.pack(AL_INIT | AL_ERROR), timeout)  # the error bit acknowledges
            slave._fpwr(REG_EEPROM_CONFIG, EEPROM_TO_PDI, timeout)
            state = self._await_state(slave, AL_INIT)
            if state != AL_INIT:
                return state
            for address, data in setup.sync_managers:
                slave._fpwr(address, data, timeout)
            slave._fpwr(REG_AL_CONTROL, _U16.pack(AL_PRE_OP), timeout)
            state = self._await_state(slave, AL_PRE_OP)
            if state != AL_PRE_OP:
                return state
            try:
                self._map_pdos(k, release_gil=True)
            except SdoError:  # it stays in PRE-OP (flagged, "in PRE-OP") and the next pass tries again
                return state
            slave._fpwr(REG_AL_CONTROL, _U16.pack(AL_SAFE_OP), timeout)
            state = self._await_state(slave, AL_SAFE_OP)
            for address, data in setup.fmmus:
                slave._fpwr(address, data, timeout)
            return state
        except pysoem.WkcError:
            return 0

    def _await_state(self, slave: pysoem.CdefSlave, wanted: int) -> int:
        """Poll the slave's AL status until it shows ``wanted``, refuses (error flag), the wait runs out or the
        master closes; returns the state (without the error flag). One frame per read, the lock free between."""
        deadline = time.monotonic() + STATE_CHANGE_TIMEOUT_S
        while True:
            try:
                status = _U16.unpack(slave._fprd(REG_AL_STATUS, 2))[0]
            except pysoem.WkcError:
                status = 0
            state = status & 0x0F
            if state == wanted or status & AL_ERROR or time.monotonic() > deadline or self._stop.wait(STATE_POLL_S):
                return state

    @property
    def lost(self) -> np.ndarray:
        """Ring positions the supervision found not answering at all (copy)."""
        return self._lost.copy()

    # ----------------------------------------------------------------------------------- SDO
    def _sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        slave = self._pslaves[position]
        return self._transfer(position, index, sub_index,
                              lambda: slave.sdo_read(index, sub_index, release_gil=True))

    def _sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        slave = self._pslaves[position]
        self._transfer(position, index, sub_index, lambda: slave.sdo_write(index, sub_index, data, release_gil=True))

    def _transfer(self, position: int, index: int, sub_index: int, call: Callable[[], object]):
        """Run one pysoem transfer for ``position``; route errors popped in the wrong thread; retry lost frames.

        A working counter <= 0 that comes back well before the mailbox timeout means a frame of the
        exchange was lost (EC_NOFRAME/EC_OTHERFRAME), not that the slave stayed silent; the transfer is
        repeated then (SOEM empties a stale reply from the slave's mailbox first, and every object Prime
        writes takes the same value twice).
        """
        with self._locks[position], self._in_flight_slots:
            for _ in range(TRANSFER_ATTEMPTS):
                started = self._clock()
                try:
                    return call()
                except (pysoem.SdoError, pysoem.MailboxError, pysoem.PacketError) as exc:
                    if exc.slave_pos - 1 == position:
                        raise _sdo_error(position, index, sub_index, exc) from None
                    with self._stray_lock:  # another slave's error popped here: hand it over, retry ours
                        self._stray[exc.slave_pos - 1] = exc
                except pysoem.WkcError as exc:
                    with self._stray_lock:
                        stray = self._stray.pop(position, None)
                    if stray is not None:
                        raise _sdo_error(position, index, sub_index, stray) from None
                    if (self._clock() - started) * 1e6 < self.sdo_timeout_us / 2:
                        self.lost_frames += 1
                        continue
                    raise SdoError(position, index, sub_index,
                                   f"no reply within {self.sdo_timeout_us / 1e3:g} ms (mailbox timeout, "
                                   f"working counter {exc.wkc})") from None
                except AssertionError:  # pysoem's upload found another slave's error first; retry
                    continue
        raise SdoError(position, index, sub_index, f"no complete exchange in {TRANSFER_ATTEMPTS} attempts "
                                                   "(frames lost or other slaves' errors interleaving)")

    def _on_emergency(self, emergency: pysoem.Emergency) -> None:
        self.emergencies[emergency.slave_pos - 1] = emergency.error_code

    # --------------------------------------------------------------------------------- close
    def _close(self) -> None:
        self._stop.set()
        self._check.set()
        if self._supervisor is not None:
            self._supervisor.join()
            self._supervisor = None
        m, self._m = self._m, None
        self._socket = None
        if m is None:
            return
        try:
            if self._pslaves:
                m.state = pysoem.INIT_STATE
                m.write_state()
        finally:
            m.close()
            self._pslaves = []

    def _require(self) -> pysoem.Master:
        if self._m is None:
            raise RingError(f"EtherCAT master on {self.interface} is not open")
        return self._m


def _signed64(value: int) -> int:
    value &= 0xFFFFFFFFFFFFFFFF
    return value - (1 << 64) if value >= 1 << 63 else value


def _push_toward_op(slave: pysoem.CdefSlave, state: int) -> bool:
    """One step toward OP for a slave in SAFE-OP: acknowledge an error, else request OP. False otherwise."""
    if state == AL_SAFE_OP | AL_ERROR:
        slave.state = pysoem.SAFEOP_STATE | pysoem.STATE_ACK
    elif state == AL_SAFE_OP:
        slave.state = pysoem.OP_STATE
    else:
        return False
    slave.write_state()
    return True


def _describe(exc: BaseException) -> str:
    if isinstance(exc, pysoem.SdoError):
        return f"0x{exc.index:04X}:{exc.subindex:02X} aborted with 0x{exc.abort_code:08X} ({exc.desc})"
    if isinstance(exc, pysoem.MailboxError):
        return f"mailbox error {exc.error_code} ({exc.desc})"
    if isinstance(exc, pysoem.PacketError):
        return f"unexpected mailbox reply (packet error {exc.error_code})"
    if isinstance(exc, pysoem.WkcError):
        return "no reply (working counter 0)"
    return str(exc) or type(exc).__name__


def _sdo_error(position: int, index: int, sub_index: int, exc: Exception) -> SdoError:
    if isinstance(exc, pysoem.SdoError):
        return SdoError(position, index, sub_index, f"aborted with 0x{exc.abort_code:08X} ({exc.desc})",
                        exc.abort_code)
    return SdoError(position, index, sub_index, _describe(exc))


def packet_sockets(interface: str) -> set[int]:
    """File descriptors of this process's raw packet sockets bound to ``interface`` (from ``/proc``); empty
    where ``/proc`` cannot tell."""
    try:
        index = socket.if_nametoindex(interface)
        with open("/proc/net/packet") as table:
            next(table)  # sk RefCnt Type Proto Iface R Rmem User Inode
            inodes = {f"socket:[{fields[8]}]" for fields in map(str.split, table) if int(fields[4]) == index}
        found = set()
        for name in os.listdir("/proc/self/fd"):
            try:
                if os.readlink(f"/proc/self/fd/{name}") in inodes:
                    found.add(int(name))
            except OSError:  # closed meanwhile
                continue
        return found
    except (OSError, StopIteration, IndexError, ValueError):
        return set()


def threaded_receive(interface: str, *, kernel_version: str | None = None, root: Path = Path("/")) -> str | None:
    """Why frames on ``interface`` reach the socket through a kernel thread (None where they come in interrupt
    context): a PREEMPT_RT kernel or one booted with ``threadirqs`` runs interrupt handlers in threads, and a
    NIC in threaded NAPI mode polls from a kernel thread of normal priority."""
    version = os.uname().version if kernel_version is None else kernel_version
    if "PREEMPT_RT" in version or _read(root / "sys/kernel/realtime") == "1":
        return "a PREEMPT_RT kernel runs the NIC's interrupts in threads"
    if "threadirqs" in _read(root / "proc/cmdline").split():
        return "the kernel was booted with threadirqs"
    if _read(root / "sys/class/net" / interface / "threaded") == "1":
        return f"{interface} runs NAPI in a kernel thread"
    return None


def _read(path: Path) -> str:
    """A small kernel file's text, stripped; '' where there is none."""
    try:
        return path.read_text().strip()
    except OSError:
        return ""
