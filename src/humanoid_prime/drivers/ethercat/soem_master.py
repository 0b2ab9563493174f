"""The EtherCAT master on a raw NIC: SOEM through pysoem for the ring scan, the PDO layout, the distributed clocks'
measurement and the cycle; Prime's own frames for everything else.

The parts, each with its module:

- the cycle (``send``/``receive``), run by the controller manager's thread, is SOEM's process data; pysoem releases
  the interpreter lock while it waits for the frame;
- register access and every mailbox transfer go in frames of our own (``registers.py`` over ``link.py``, CoE in
  ``mailbox.py``), each reply matched to its request, because SOEM files a late reply as the answer to a later
  request (``link.py`` says how). SDOs run in the caller's thread, one per slave at once;
- the PDO mapping in PRE-OP, and the check of what SOEM laid out from it (``mapping.py``): a bring-up whose
  layout, clocks or SAFE-OP went wrong in a way a slow ring or a late reply explains is configured again from a
  fresh ring scan, at most ``CONFIGURE_ATTEMPTS`` times, each reason kept (``configure_attempts``); a drive that
  refuses the mapping is not asked again;
- the distributed clocks and SYNC0 (``clocks.py``); supervision and recovery once in OP (``supervision.py``).

SOEM's socket. SOEM polls its socket for each frame it waits for ("non blocking call to retrieve frame from
socket", oshw/linux/nicdrv.c) but opens it blocking with a 1 µs receive timeout, which the kernel rounds up to
whole scheduler ticks. Blocking, a lost frame holds its thread for those ticks instead of the 2 ms frame timeout,
and a thread whose frame another thread has already filed sleeps in ``recv`` until some other frame arrives.
``poll_frames`` makes the socket non-blocking, so each waiting thread polls until its frame is filed or its timeout
passes. It is for the time the control loop's real-time thread owns the cycle: the bring-up loop, the drives'
enabling and the keeper sleep on the socket (at ``FEEDING_PRIORITY``, where permitted): a thread polling below the
loop's priority would use up what the kernel lets real-time threads run. Nor does the master poll where the kernel
delivers the NIC's frames from a thread (``threaded_receive``): a real-time thread polling on that thread's CPU
would keep it from delivering the very frame it waits for. The socket also gets a filter that keeps our replies out
of its queue.
"""

from __future__ import annotations

import contextlib
import os
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pysoem

from humanoid_prime.drivers.ethercat.clocks import RingClocks
from humanoid_prime.drivers.ethercat.errors import RingError, SdoError
from humanoid_prime.drivers.ethercat.link import LateReply, SocketWire, Wire, filter_soem_socket
from humanoid_prime.drivers.ethercat.mailbox import CoeMailbox, MailboxLayout
from humanoid_prime.drivers.ethercat.mapping import EscSetup, PdoMapping, mailbox_sync_managers, read_esc_setup
from humanoid_prime.drivers.ethercat.master import RX_DTYPE, TX_DTYPE, EthercatMaster
from humanoid_prime.drivers.ethercat.registers import NoReply, RingRegisters
from humanoid_prime.drivers.ethercat.ring import SlaveInfo, describe_states
from humanoid_prime.drivers.ethercat.supervision import RingSupervisor
from humanoid_prime.drivers.ethercat.wire import AL_ERROR, AlState

STATE_TIMEOUT_S = 3.0  # PRE-OP and SAFE-OP for the whole ring, before the cycle starts
SCAN_ATTEMPTS = 3  # ring scans when SOEM finds fewer slaves than answer our own broadcast read
SCAN_PATIENCE_S = 0.5  # how long our broadcast read waits for a ring that answers late
CONFIGURE_ATTEMPTS = 3  # configurations from a fresh ring scan, when one went wrong the way a late reply explains
STATE_POLL_S = 0.001
_U16 = struct.Struct("<H")


class Reconfigure(Exception):
    """A configuration that went wrong the way a slow ring or a late reply explains: configure again."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def socket_wire(interface: str, indices: range) -> Wire:
    return SocketWire(interface, indices.start, indices.stop - 1)


class SoemMaster(EthercatMaster):
    """pysoem on the NIC named in ``prime_hardware.yaml`` (``buses.ethercat.interface``). ``wire(interface,
    indices)`` opens the wire of one of our channels (a raw socket; the tests' doubles pass frames in-process)."""

    supervise_period_s = 0.1  # how often the supervision reads every slave's AL state once in OP

    def __init__(self, interface: str, *, update_rate: float, bringup_rate: float = 1000.0,
                 sync0_period_s: float | None = None, bringup_timeout_s: float = 30.0, parallel_sdo: bool = True,
                 sdo_in_flight: int | None = None, sdo_timeout_s: float = 0.7, frame_timeout_us: int = 2000,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], object] = time.sleep,
                 wire: Callable[[str, range], Wire] = socket_wire,
                 configure_attempts: int = CONFIGURE_ATTEMPTS) -> None:
        super().__init__(interface, update_rate=update_rate, bringup_rate=bringup_rate,
                         sync0_period_s=sync0_period_s, bringup_timeout_s=bringup_timeout_s, clock=clock, sleep=sleep)
        self.parallel_sdo = parallel_sdo
        # transfers in flight at once over the ring: one per slave unless capped (or 1 when not parallel)
        self.sdo_in_flight = (sdo_in_flight or 64) if parallel_sdo else 1
        self._in_flight_slots = threading.BoundedSemaphore(self.sdo_in_flight)
        self.sdo_timeout_s = sdo_timeout_s
        self.frame_timeout_us = frame_timeout_us
        self.configure_attempts = configure_attempts
        self._wire = wire
        self.emergencies: dict[int, int] = {}  # ring position -> last EMCY error code
        self.threaded_receive: str | None = None  # why the NIC's frames arrive through a kernel thread, if they do
        self.configure_reasons: list[str] = []  # why each configuration that was not the last went again
        self.scan_reasons: list[str] = []  # why ring scans were repeated
        self.registers: RingRegisters | None = None
        self.supervisor: RingSupervisor | None = None
        self._closing = threading.Event()
        self._socket: int | None = None  # SOEM's socket, where it could be told from this process's others
        self._m: pysoem.Master | None = None
        self._pslaves: list[pysoem.CdefSlave] = []
        self._mailboxes: list[CoeMailbox] = []
        self._mapping: PdoMapping | None = None
        self._setups: list[EscSetup] = []
        self._clocks: RingClocks | None = None
        self._out_buf = bytearray()
        self._in_buf = bytearray()
        self._out_pairs: list[tuple[pysoem.CdefSlave, memoryview]] = []  # (pysoem slave, its output bytes)
        self._in_pairs: list[tuple[pysoem.CdefSlave, slice]] = []  # type: ignore[explicit-any]  # pysoem ships no types

    # ---------------------------------------------------------------------------------------- what it saw
    @property
    def soem_socket(self) -> int | None:
        """SOEM's socket (a file descriptor), where it could be told from this process's other packet sockets."""
        return self._socket

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

    # ---------------------------------------------------------------------------------------- discovery
    def _discover(self) -> Sequence[SlaveInfo]:
        self._closing.clear()
        try:
            socket.if_nametoindex(self.interface)
        except OSError:
            raise RingError(f"no network interface {self.interface!r} (buses.ethercat.interface in "
                            "prime_hardware.yaml); list them with `ip link` or pass --interface") from None
        self._scan()
        return self._await_ring_state(AlState.PRE_OP, "did not reach PRE-OP")

    def _scan(self) -> None:
        """Open SOEM on the NIC and let it scan the ring; again while it finds fewer slaves than answer our own
        broadcast read (its frames came back later than its 2 ms frame timeout: a busy host or a slow ring)."""
        for attempt in range(1, SCAN_ATTEMPTS + 1):
            m = self._open_soem()
            found = m.config_init()
            answered, waited = self._count()
            if found > 0 and found >= (answered or 0):
                break
            self._close_soem()
            if not answered:
                raise RingError(f"no EtherCAT slave answered on {self.interface} (a broadcast read waited "
                                f"{SCAN_PATIENCE_S * 1e3:g} ms): check the cable and the drives' power, and that "
                                "no other master (IgH) owns this NIC")
            self.scan_reasons.append(f"scan {attempt}: SOEM found {max(found, 0)} slaves, {answered} answered a "
                                     f"broadcast read after {waited * 1e3:.1f} ms")
        else:
            raise RingError(f"{answered} EtherCAT slaves answer on {self.interface}, but SOEM's ring scan found "
                            f"{max(found, 0)} in {SCAN_ATTEMPTS} tries: its frames came back later than its 2 ms "
                            "frame timeout (a busy host, or a slow ring); "
                            + "; ".join(self.scan_reasons))
        self._pslaves = list(m.slaves)
        for slave in self._pslaves:
            slave.add_emergency_callback(self._on_emergency)
        self.registers = RingRegisters(lambda indices: self._wire(self.interface, indices), len(self._pslaves),
                                       clock=self.clock)
        wrong = self.registers.check_stations()
        if wrong:
            raise RingError(f"ring {', '.join(map(str, wrong))} on {self.interface} do not answer at the station "
                            "address SOEM gave them")

    def _open_soem(self) -> pysoem.Master:
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
        if self._socket is not None:
            filter_soem_socket(self._socket)
        self.threaded_receive = threaded_receive(self.interface)
        m.sdo_read_timeout = m.sdo_write_timeout = round(self.sdo_timeout_s * 1e6)
        return m

    def _count(self) -> tuple[int | None, float]:
        """(slaves that answer a broadcast read of ours, how long it took); the read waits ``SCAN_PATIENCE_S``."""
        probe = RingRegisters(lambda indices: self._wire(self.interface, indices), 1, clock=self.clock)
        try:
            began = self.clock()
            answered = probe.count(SCAN_PATIENCE_S)
            return answered, self.clock() - began
        finally:
            probe.close()

    def _await_ring_state(self, want: int, what: str) -> list[SlaveInfo]:
        """Every slave's AL state, polled until all show ``want`` (or one refuses it, or ``STATE_TIMEOUT_S``)."""
        deadline = self.clock() + STATE_TIMEOUT_S
        while True:
            states = self._registers().states()
            if states is not None and all(s is not None and s[0] == want for s in states):
                break
            if (states is not None and any(s is not None and s[0] & AL_ERROR for s in states)) \
                    or self.clock() > deadline:
                break
            self.sleep(STATE_POLL_S)
        found = [SlaveInfo(k, s.name, s.man, s.id, s.rev, *((states[k] if states else None) or (0, 0)))
                 for k, s in enumerate(self._pslaves)]
        if all(info.al_state == want for info in found):
            return found
        self._store_found(found)
        if want == AlState.PRE_OP:  # straight after a scan: nothing of ours has touched the slaves yet
            raise RingError(f"EtherCAT ring on {self.interface} {what}: {describe_states(found, want)}")
        raise Reconfigure(f"the ring {what}: {describe_states(found, want)}")

    def _store_found(self, found: Sequence[SlaveInfo]) -> None:
        if len(self.al_state) == len(found):
            for info in found:
                self.al_state[info.position] = info.al_state
                self.al_status_code[info.position] = info.al_status_code

    # -------------------------------------------------------------------------------------- configuration
    def _configure(self) -> None:
        """Map, lay out, clock and reach SAFE-OP; again from a fresh scan when it went wrong the way a late reply
        or a slow ring explains (``Reconfigure``), at most ``configure_attempts`` times."""
        for attempt in range(1, self.configure_attempts + 1):
            began = self.clock()
            try:
                self._configure_once()
                return
            except Reconfigure as exc:
                late = self._lateness(began)
                self.configure_reasons.append(f"attempt {attempt}: {exc.reason}{late}")
            if attempt < self.configure_attempts:
                self._rescan()
        raise RingError(f"configuring the EtherCAT ring on {self.interface} failed {self.configure_attempts} times: "
                        + "; ".join(self.configure_reasons))

    def _lateness(self, since: float) -> str:
        late = self.late_replies(since)
        dropped = [d for mailbox in self._mailboxes for d in mailbox.dropped if d.at >= since]
        if not late and not dropped:
            return ""
        words = []
        if late:
            words.append(f"{len(late)} register or mailbox frames came back late (the latest "
                         f"{max(x.late_s for x in late) * 1e3:.0f} ms after it was sent)")
        if dropped:
            words.append(f"{len(dropped)} mailbox replies came late and were dropped (the latest "
                         f"{max(d.waited_s for d in dropped) * 1e3:.0f} ms after a request)")
        return " (" + "; ".join(words) + ")"

    def _rescan(self) -> None:
        """Back to INIT and a fresh ring scan, which must find the same ring."""
        before = [(s.man, s.id) for s in self._pslaves]
        self._close_soem()
        self._scan()
        if [(s.man, s.id) for s in self._pslaves] != before:
            raise RingError(f"the EtherCAT ring on {self.interface} changed while it was being configured again: "
                            f"{len(before)} slaves before, {len(self._pslaves)} now")
        self._await_ring_state(AlState.PRE_OP, "did not reach PRE-OP")

    def _configure_once(self) -> None:
        m, registers = self._require(), self._registers()
        n = len(self._pslaves)
        try:
            layouts = [MailboxLayout(*mailbox_sync_managers(registers, k)) for k in range(n)]
        except NoReply as exc:
            raise Reconfigure(f"the mailbox SyncManagers could not be read ({exc.what})") from None
        self._mailboxes = [CoeMailbox(registers.channel(k), k, registers.stations[k], layouts[k], clock=self.clock,
                                      sleep=self.sleep, on_emergency=self._store_emergency) for k in range(n)]
        self._mapping = PdoMapping(self._mailboxes, self.sdo_timeout_s, self._store_rated)
        for slave in self._pslaves:
            slave.config_func = self._mapping.hook
        m.manual_state_change = 1  # config_map must not ask for SAFE-OP before SYNC0 is set
        try:
            m.config_map()
        except pysoem.ConfigMapError as exc:
            raise Reconfigure("SOEM could not read the PDO mapping back: "
                              + "; ".join(_describe(e) for e in exc.error_list)) from None
        except Exception as exc:
            refused = [p for p in self._mapping.problems.values() if "refused" in p]
            problems = "; ".join(self._mapping.problems.values()) or _describe(exc)
            if refused:
                raise RingError(f"mapping the PDOs on {self.interface} failed: {problems}") from None
            raise Reconfigure(f"mapping the PDOs failed: {problems}") from None
        finally:
            for mailbox in self._mailboxes:
                mailbox.shared()  # SOEM read the mapping back through them
        for k, slave in enumerate(self._pslaves):
            problem = self._mapping.check(k, (len(slave.output), len(slave.input)))
            if problem is not None:
                raise Reconfigure(problem)
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
        self._await_ring_state(AlState.SAFE_OP, "did not reach SAFE-OP")
        self.expected_wkc = m.expected_wkc
        self._out_buf = bytearray(n * RX_DTYPE.itemsize)
        self._in_buf = bytearray(n * TX_DTYPE.itemsize)
        self.outputs = np.frombuffer(self._out_buf, dtype=RX_DTYPE)
        self.inputs = np.frombuffer(self._in_buf, dtype=TX_DTYPE)
        view = memoryview(self._out_buf)
        out_size, in_size = RX_DTYPE.itemsize, TX_DTYPE.itemsize
        self._out_pairs = [(s, view[k * out_size:(k + 1) * out_size]) for k, s in enumerate(self._pslaves)]
        self._in_pairs = [(s, slice(k * in_size, (k + 1) * in_size)) for k, s in enumerate(self._pslaves)]

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
        # a returning slave's state changes: on the master's clock; in production the wait ends when it closes
        pause = self._closing.wait if self.sleep is time.sleep else self.sleep
        assert self._clocks is not None  # armed by the configuration
        self.supervisor = RingSupervisor(self, self._registers(), self._clocks, self._setups,
                                         remap=self._remap, recover=self._recover, wkc=lambda: self.wkc,
                                         sync0_ns=self.sync0_ns, period_s=self.supervise_period_s,
                                         name=f"ethercat-supervise-{self.interface}", clock=self.clock, pause=pause)
        self.supervisor.start()

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

    def poll_frames(self, poll: bool) -> bool:
        if self._socket is None or self._m is None or (poll and self.threaded_receive is not None):
            return False
        os.set_blocking(self._socket, not poll)
        return poll

    # -------------------------------------------------------------------------------------------- cyclic
    def _send(self) -> None:
        m = self._m
        assert m is not None  # cyclic exchange runs between open and close
        for slave, view in self._out_pairs:
            slave.output = bytes(view)
        m.send_processdata()

    def _receive(self) -> int:
        m = self._m
        assert m is not None  # as in _send
        wkc: int = m.receive_processdata(self.frame_timeout_us, release_gil=True)
        buf = self._in_buf
        for slave, where in self._in_pairs:
            buf[where] = slave.input
        return wkc

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
        self._socket = None
        registers, self.registers = self.registers, None
        try:
            if m is not None and self._pslaves:
                m.state = pysoem.INIT_STATE
                m.write_state()
        finally:
            if m is not None:
                m.close()
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


def _describe(exc: BaseException) -> str:
    if isinstance(exc, pysoem.SdoError):
        return f"0x{exc.index:04X}:{exc.subindex:02X} aborted with 0x{exc.abort_code:08X} ({exc.desc})"
    if isinstance(exc, pysoem.MailboxError):
        return f"mailbox error {exc.error_code} ({exc.desc})"
    if isinstance(exc, pysoem.PacketError):
        return f"unexpected mailbox reply (packet error {exc.error_code})"
    if isinstance(exc, pysoem.WkcError):
        return "no reply (working counter 0)"
    if isinstance(exc, SdoError):
        return str(exc)
    return str(exc) or type(exc).__name__


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
