"""The EtherCAT master on a raw NIC: SOEM through pysoem for the ring scan, the PDO layout, the distributed clocks'
measurement and the cycle; Prime's own frames, beside SOEM's, for everything else. What Prime's frames beside
SOEM's rest on is ``soem_contract.py``'s, checked when the ring is opened.

- the scan (``soem_scan.py``): SOEM's, repeated while it finds fewer slaves than answer, or reads an identity its
  slave's SII does not hold;
- the cycle (``send``/``receive``), run by the controller manager's thread, is SOEM's process data; pysoem releases
  the interpreter lock while it waits for the frame. SOEM's socket is SOEM's: blocking, with the 1 µs receive timeout
  it sets (the kernel rounds it to a scheduler tick);
- register access and every mailbox transfer go in frames of our own (``registers.py`` over ``link.py``, CoE in
  ``mailbox.py``), each reply matched to its request, because SOEM files a late reply as the answer to a later
  request (``link.py`` says how). SDOs run in the caller's thread, one per slave at once. With ``mailbox="soem"``
  (``buses.ethercat.mailbox: soem``) SOEM does the mailbox work alone (``soem_mailbox.py``);
- the PDO mapping in PRE-OP, and the check of what SOEM laid out from it (``mapping.py``): a bring-up whose layout,
  clocks or SAFE-OP went wrong in a way a slow ring or a late reply explains is configured again from a fresh ring
  scan, at most ``CONFIGURE_ATTEMPTS`` times, each reason kept (``configure_reasons``); a drive that refuses the
  mapping is not asked again;
- each change of AL state is waited for as long as the standard lets it take, and a refusal named with its AL status
  code (``states.py``);
- the distributed clocks and SYNC0 (``clocks.py``); supervision and recovery once in OP (``supervision.py``).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Sequence

import numpy as np
import numpy.typing as npt
import pysoem

from humanoid_prime.config.hardware import MAILBOXES
from humanoid_prime.drivers.ethercat.clocks import RingClocks
from humanoid_prime.drivers.ethercat.errors import RingError
from humanoid_prime.drivers.ethercat.link import LateReply, SocketWire, Wire
from humanoid_prime.drivers.ethercat.mailbox import CoeMailbox, DropLog, MailboxLayout, SdoMailbox
from humanoid_prime.drivers.ethercat.mapping import EscSetup, PdoMapping, mailbox_sync_managers, read_esc_setup
from humanoid_prime.drivers.ethercat.master import RX_DTYPE, TX_DTYPE, EthercatMaster
from humanoid_prime.drivers.ethercat.registers import NoReply, RingRegisters
from humanoid_prime.drivers.ethercat.ring import SlaveInfo
from humanoid_prime.drivers.ethercat.soem_contract import FrameWatch, QueueKeeper, SocketWatch
from humanoid_prime.drivers.ethercat.soem_mailbox import SoemMailbox, describe_soem_error
from humanoid_prime.drivers.ethercat.soem_scan import Identity, SoemScan, close_soem, soem_identity
from humanoid_prime.drivers.ethercat.states import StateWait, await_state
from humanoid_prime.drivers.ethercat.supervision import RingSupervisor
from humanoid_prime.drivers.ethercat.wire import AL_ERROR, AlState

CONFIGURE_ATTEMPTS = 3  # configurations from a fresh ring scan, when one went wrong the way a late reply explains
STATE_POLL_S = 0.001


class Reconfigure(Exception):
    """A configuration that went wrong the way a slow ring or a late reply explains: configure again."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def socket_wire(interface: str, indices: range) -> Wire:
    return SocketWire(interface, indices.start, indices.stop - 1)


class SoemMaster(EthercatMaster):
    """pysoem on the NIC named in ``prime_hardware.yaml`` (``buses.ethercat.interface``). ``wire(interface,
    indices)`` opens the wire of one of our channels and ``watch(interface)`` a watch on the NIC (raw sockets; the
    tests' doubles pass frames in-process)."""

    supervise_period_s = 0.1  # how often the supervision reads every slave's AL state once in OP

    def __init__(self, interface: str, *, update_rate: float, bringup_rate: float = 1000.0,
                 sync0_period_s: float | None = None, bringup_timeout_s: float = 30.0, parallel_sdo: bool = True,
                 sdo_in_flight: int | None = None, sdo_timeout_s: float = 0.7, frame_timeout_us: int = 2000,
                 mailbox: str = "prime", clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], object] = time.sleep, wire: Callable[[str, range], Wire] = socket_wire,
                 watch: Callable[[str], FrameWatch] = SocketWatch,
                 configure_attempts: int = CONFIGURE_ATTEMPTS) -> None:
        super().__init__(interface, update_rate=update_rate, bringup_rate=bringup_rate,
                         sync0_period_s=sync0_period_s, bringup_timeout_s=bringup_timeout_s, clock=clock, sleep=sleep)
        if mailbox not in MAILBOXES:
            raise RingError(f"unknown mailbox {mailbox!r}: use one of {', '.join(MAILBOXES)}")
        self.mailbox = mailbox
        self.parallel_sdo = parallel_sdo
        # transfers in flight at once over the ring: one per slave unless capped (or 1 when not parallel)
        self.sdo_in_flight = (sdo_in_flight or 64) if parallel_sdo else 1
        self._in_flight_slots = threading.BoundedSemaphore(self.sdo_in_flight)
        self.sdo_timeout_s = sdo_timeout_s
        self.frame_timeout_us = frame_timeout_us
        self.configure_attempts = configure_attempts
        self.drops = DropLog()  # what the mailboxes dropped, by why
        self.emergencies: dict[int, int] = {}  # ring position -> last EMCY error code
        self.configure_reasons: list[str] = []  # why each configuration that was not the last went again
        self.queue = QueueKeeper(self._drain_soem)
        self.registers: RingRegisters | None = None
        self.supervisor: RingSupervisor | None = None
        self._scanner = SoemScan(interface, wire=wire, watch=watch, sdo_timeout_s=sdo_timeout_s, clock=clock,
                                 on_sent=self.queue.sent)
        self._closing = threading.Event()
        self._cycling = False  # SOEM's cycle runs: its receives read its socket
        self._m: pysoem.Master | None = None
        self._pslaves: list[pysoem.CdefSlave] = []
        self._mailboxes: list[SdoMailbox] = []
        self._soem_lock = threading.Lock()  # SOEM's transfers, one at a time on the ring
        self._mapping: PdoMapping | None = None
        self._setups: list[EscSetup] = []
        self._clocks: RingClocks | None = None
        self._out_buf = bytearray()
        self._in_buf = bytearray()
        self._out_pairs: list[tuple[pysoem.CdefSlave, memoryview]] = []  # (pysoem slave, its output bytes)
        self._in_pairs: list[tuple[pysoem.CdefSlave, slice]] = []  # type: ignore[explicit-any]  # pysoem ships no types

    # ---------------------------------------------------------------------------------------- what it saw
    @property
    def scan_reasons(self) -> list[str]:
        """Why ring scans were repeated."""
        return self._scanner.reasons

    @property
    def lost(self) -> npt.NDArray[np.bool_]:
        """Ring positions the supervision found not answering at all (copy)."""
        return self.supervisor.lost.copy() if self.supervisor is not None else np.zeros(len(self.slaves), bool)

    @property
    def recoveries(self) -> int:
        return self.supervisor.recoveries if self.supervisor is not None else 0

    @property
    def supervision_error(self) -> str | None:
        return self.supervisor.error if self.supervisor is not None else None

    @property
    def lost_frames(self) -> int:
        """Frames of ours that did not come back in time (each was sent again, or its exchange given up)."""
        return 0 if self.registers is None else self.registers.frames_lost()

    def late_replies(self, since: float = 0.0) -> list[LateReply]:
        """Replies to our frames that came after their frame was given up on (``clock`` time)."""
        return self.registers.late_since(since) if self.registers is not None else []

    def mailbox_drops(self) -> dict[str, int]:
        return self.drops.snapshot()

    def mailbox_given_up(self) -> int:
        return self.drops.given_up

    # ---------------------------------------------------------------------------------------- discovery
    def _discover(self) -> Sequence[SlaveInfo]:
        self._closing.clear()
        self._open()
        found = self._await_ring_state(AlState.PRE_OP)
        if not found.reached:  # straight after a scan: nothing of ours has touched the slaves yet
            raise RingError(f"EtherCAT ring on {self.interface} did not reach PRE-OP: {found.describe()}")
        return self._found(found)

    def _open(self, before: Sequence[Identity] | None = None) -> None:
        m, self.registers = self._scanner.scan(before)
        self._m = m
        self._pslaves = list(m.slaves)
        for slave in self._pslaves:
            slave.add_emergency_callback(self._on_emergency)

    def _await_ring_state(self, want: int) -> StateWait:
        """Every slave's AL state, polled until all show ``want``, one refuses it, or the standard's time for the
        change has passed; the states are stored."""
        registers = self._registers()
        wait = await_state(registers.states, lambda k, state: _ask(registers, k, state), len(self._pslaves), want,
                           clock=self.clock, sleep=self.sleep)
        if len(self.al_state) == len(wait.states):
            for k, state in enumerate(wait.states):
                self.al_state[k], self.al_status_code[k] = state if state is not None else (0, 0)
        return wait

    def _found(self, wait: StateWait) -> list[SlaveInfo]:
        return [SlaveInfo(k, s.name, s.man, s.id, s.rev, *(wait.states[k] or (0, 0)))
                for k, s in enumerate(self._pslaves)]

    # -------------------------------------------------------------------------------------- configuration
    def _configure(self) -> None:
        """Map, lay out, clock and reach SAFE-OP; again from a fresh scan when it went wrong the way a late reply
        or a slow ring explains (``Reconfigure``), at most ``configure_attempts`` times."""
        for attempt in range(1, self.configure_attempts + 1):
            began, drops = self.clock(), self.drops.snapshot()
            try:
                self._configure_once()
                return
            except Reconfigure as exc:
                self.configure_reasons.append(f"attempt {attempt}: {exc.reason}{self._what_went_by(began, drops)}")
            if attempt < self.configure_attempts:
                self._rescan()
        raise RingError(f"configuring the EtherCAT ring on {self.interface} failed {self.configure_attempts} times: "
                        + "; ".join(self.configure_reasons))

    def _what_went_by(self, since: float, drops: dict[str, int]) -> str:
        """The frames that came back late and the mailbox messages dropped since ``since``, in words."""
        late = self.late_replies(since)
        words = []
        if late:
            words.append(f"{len(late)} register or mailbox frames came back late (the latest "
                         f"{max(x.late_s for x in late) * 1e3:.0f} ms after it was sent)")
        dropped = self.drops.describe(drops, since)
        if dropped:
            words.append(f"mailbox messages dropped: {dropped}")
        return f" ({'; '.join(words)})" if words else ""

    def _rescan(self) -> None:
        """Back to INIT and a fresh ring scan, which must find the same ring."""
        before = [soem_identity(slave) for slave in self._pslaves]
        self._close_soem()
        self._open(before)
        wait = self._await_ring_state(AlState.PRE_OP)
        if not wait.reached:
            raise RingError(f"EtherCAT ring on {self.interface} did not reach PRE-OP when configured again: "
                            f"{wait.describe()}")

    def _configure_once(self) -> None:
        m, registers = self._require(), self._registers()
        n = len(self._pslaves)
        self._mailboxes = self._open_mailboxes(registers)
        self._mapping = PdoMapping(self._mailboxes, self.sdo_timeout_s, self._store_rated)
        for slave in self._pslaves:
            slave.config_func = self._mapping.hook
        m.manual_state_change = 1  # config_map must not ask for SAFE-OP before SYNC0 is set
        read_back = ""
        try:
            m.config_map()
        except pysoem.ConfigMapError as exc:
            # pysoem raises it for any error SOEM listed, a slave's emergency too, after the layout is done: the
            # layout is checked below either way, and these are only the why if it is wrong
            read_back = "; SOEM's read-back of the mapping reported " + "; ".join(
                sorted({describe_soem_error(e) for e in exc.error_list}))
        except Exception as exc:
            refused = [p for p in self._mapping.problems.values() if "refused" in p]
            problems = "; ".join(self._mapping.problems.values()) or describe_soem_error(exc)
            if refused:
                raise RingError(f"mapping the PDOs on {self.interface} failed: {problems}") from None
            raise Reconfigure(f"mapping the PDOs failed: {problems}") from None
        finally:
            for mailbox in self._mailboxes:
                mailbox.reset_counter()  # SOEM read the mapping back through them
        for k, slave in enumerate(self._pslaves):
            problem = self._mapping.check(k, (len(slave.output), len(slave.input)))
            if problem is not None:
                raise Reconfigure(problem + read_back)
        if not m.config_dc():
            raise RingError(f"no slave on {self.interface} supports distributed clocks; eRob CSP needs DC "
                            "(CSP in free run faults the drives with 4616)")
        try:
            self._setups = [read_esc_setup(registers, k) for k in range(n)]
        except NoReply as exc:
            raise Reconfigure(f"{exc.what}: the SyncManager, FMMU and clock registers did not answer in time, so "
                              "they could not be kept to reconfigure the slave should it lose power") from None
        self._clocks = clocks = RingClocks(registers, [s.dc for s in self._setups], [s.dc_delay for s in self._setups],
                                           self._await_cycles)
        try:
            for k in range(n):
                clocks.arm_sync0(k, self.sync0_ns)
        except NoReply as exc:
            raise Reconfigure(f"SYNC0 could not be armed: {exc.what}") from None
        registers.request_all(AlState.SAFE_OP)
        wait = self._await_ring_state(AlState.SAFE_OP)
        if not wait.reached:
            raise Reconfigure(f"the ring did not reach SAFE-OP: {wait.describe()}")
        self._lay_out(m)

    def _open_mailboxes(self, registers: RingRegisters) -> list[SdoMailbox]:
        """Each slave's mailbox: Prime's over our frames, or SOEM's alone."""
        if self.mailbox == "soem":
            return [SoemMailbox(slave, k, self._soem_lock) for k, slave in enumerate(self._pslaves)]
        try:
            layouts = [MailboxLayout(*mailbox_sync_managers(registers, k)) for k in range(len(self._pslaves))]
        except NoReply as exc:
            raise Reconfigure(f"the mailbox SyncManagers could not be read ({exc.what})") from None
        return [CoeMailbox(registers.channel(k), k, registers.stations[k], layout, clock=self.clock, sleep=self.sleep,
                           on_emergency=self._store_emergency, log=self.drops)
                for k, layout in enumerate(layouts)]

    def _lay_out(self, m: pysoem.Master) -> None:
        """The process image over what SOEM laid out: one slice of outputs and of inputs per slave."""
        n = len(self._pslaves)
        self.expected_wkc = m.expected_wkc
        self._out_buf = bytearray(n * RX_DTYPE.itemsize)
        self._in_buf = bytearray(n * TX_DTYPE.itemsize)
        self.outputs = np.frombuffer(self._out_buf, dtype=RX_DTYPE)
        self.inputs = np.frombuffer(self._in_buf, dtype=TX_DTYPE)
        view = memoryview(self._out_buf)
        out_size, in_size = RX_DTYPE.itemsize, TX_DTYPE.itemsize
        self._out_pairs = [(s, view[k * out_size:(k + 1) * out_size]) for k, s in enumerate(self._pslaves)]
        self._in_pairs = [(s, slice(k * in_size, (k + 1) * in_size)) for k, s in enumerate(self._pslaves)]
        self._cycling = True

    def _store_rated(self, k: int, raw: bytes | None, problem: str) -> None:
        if raw is None:
            self.rated_torque_problems[k] = problem
        else:
            self.store_rated_torque(k, raw)

    def _await_cycles(self, count: int) -> bool:
        """Wait until ``count`` more cycle frames came back answered (each brought the reference clock's time);
        False if that took more than four times as long as it should, or the master closes."""
        deadline = time.monotonic() + 4 * count * self.cycle_ns / 1e9 + 1.0
        until = self.cycles_answered + count
        while self.cycles_answered < until:
            if time.monotonic() > deadline or self._closing.wait(STATE_POLL_S):
                return False
        return True

    # ------------------------------------------------------------------------------------------- to OP
    def _request_op(self) -> None:
        self._registers().request_all(AlState.OP)

    def _read_states(self) -> list[tuple[int, int]]:
        states = self.registers.states() if self.registers is not None else None
        if states is None:
            return [(0, int(code)) for code in self.al_status_code]
        return [s if s is not None else (0, 0) for s in states]

    def _advance(self, slaves: Sequence[tuple[int, int]]) -> None:
        for k, state in slaves:
            with contextlib.suppress(NoReply):  # asked again at the next look
                self._registers().request_state(k, AlState.SAFE_OP | AL_ERROR if state & AL_ERROR else AlState.OP)

    def _started(self) -> None:
        assert self._clocks is not None  # armed by the configuration
        self.supervisor = RingSupervisor(self, self._registers(), self._clocks, self._setups,
                                         remap=self._remap, recover=self._recover, wkc=lambda: self.wkc,
                                         sync0_ns=self.sync0_ns, period_s=self.supervise_period_s,
                                         name=f"ethercat-supervise-{self.interface}", clock=self.clock,
                                         pause=self._pause)
        self.supervisor.start()

    def _pause(self, seconds: float) -> bool:
        """The supervision's wait between looks at a returning slave, on the master's clock; True once it closes."""
        self.sleep(seconds)
        return self._closing.is_set()

    def _remap(self, k: int) -> None:
        """The PDO mapping hook for a slave the supervision reconfigures."""
        assert self._mapping is not None  # made by the configuration, before the supervision starts
        self._mapping.hook(k)

    def _recover(self, k: int) -> bool:
        """A slave that stopped answering: True when it answers at its station address again (given back to it if
        it lost it in a power cycle; over our frames, not SOEM's ``ecx_recover_slave``, which holds the interpreter
        lock through SII reads of up to 20 ms each and would stall the cycle)."""
        info = self.slaves[k]
        return self._registers().readdress(k, (info.vendor_id, info.product_code, info.revision))

    # -------------------------------------------------------------------------------------------- cyclic
    def _send(self) -> None:
        m = self._m
        assert m is not None  # cyclic exchange runs between open and close
        for slave, view in self._out_pairs:
            slave.output = bytes(view)
        self.queue.sending()
        m.send_processdata()

    def _receive(self) -> int:
        m = self._m
        assert m is not None  # as in _send
        wkc: int = m.receive_processdata(self.frame_timeout_us, release_gil=True)
        self.queue.read()
        buf = self._in_buf
        for slave, where in self._in_pairs:
            buf[where] = slave.input
        return wkc

    def _drain_soem(self) -> None:
        """Have SOEM read its socket, where a cycle runs: a cycle frame now, whose receive reads up to it (before
        the cycle, a reply SOEM loses to a full queue is sent again by SOEM itself)."""
        if self._cycling and self._m is not None:
            self.refresh()

    def _wkc_mismatch(self) -> None:
        # A frame that did not come back at all (lost, or late past its timeout) says nothing about the slaves: the
        # supervision looks once frames return with a wrong count.
        if self.wkc > 0 and self.supervisor is not None:
            self.supervisor.wake()

    def check_ring(self) -> None:
        """One supervision pass now (``RingSupervisor.check_once``); for tools and tests."""
        if self.supervisor is None:
            raise RingError(f"EtherCAT ring on {self.interface} is not operational: nothing to supervise")
        self.supervisor.check_once()

    # ------------------------------------------------------------------------------------------------ SDO
    def _sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        with self._in_flight_slots:
            return self._mailboxes[position].upload(index, sub_index, self.sdo_timeout_s)

    def _sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        with self._in_flight_slots:
            self._mailboxes[position].download(index, sub_index, data, self.sdo_timeout_s)

    def _on_emergency(self, emergency: pysoem.Emergency) -> None:
        self.emergencies[emergency.slave_pos - 1] = emergency.error_code

    def _store_emergency(self, position: int, code: int) -> None:
        self.emergencies[position] = code

    # ---------------------------------------------------------------------------------------------- close
    def _close(self) -> None:
        self._closing.set()
        if self.supervisor is not None:
            self.supervisor.stop()
            self.supervisor = None
        self._close_soem()

    def _close_soem(self) -> None:
        m, self._m = self._m, None
        self._cycling = False
        registers, self.registers = self.registers, None
        try:
            if m is not None:
                close_soem(m, slaves=bool(self._pslaves))
        finally:
            if registers is not None:
                registers.close()
            self._pslaves = []
            self._mailboxes = []

    def _require(self) -> pysoem.Master:
        if self._m is None:
            raise RingError(f"EtherCAT master on {self.interface} is not open")
        return self._m

    def _registers(self) -> RingRegisters:
        if self.registers is None:
            raise RingError(f"EtherCAT master on {self.interface} is not open")
        return self.registers


def _ask(registers: RingRegisters, k: int, state: int) -> None:
    """Ask slave ``k`` for ``state`` again (a frame that did not come back: asked at the next turn)."""
    with contextlib.suppress(NoReply):
        registers.request_state(k, state)
