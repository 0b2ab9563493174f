"""The EtherCAT master interface: one ring, its process image, its states and SDO access by ring position.

``EthercatSystem`` depends on this interface only. ``SoemMaster`` (pysoem on a raw NIC) implements it,
and so does any test double. The base class owns what must be the same for every implementation:

- the ring check (identity and ring position of every slave against the hardware file);
- the SYNC0 period, derived from the loop period and never set apart from it (DESIGN §3);
- the fast bring-up loop that keeps every output fed while slaves reach OP, and after it a keeper that
  sends the current outputs whenever the owner of the cycle goes quiet;
- the SDO gate: no SDO touches the bus before every slave is in OP and process data flows, because
  mailbox traffic during DC activation faults a drive with 0xA000. The PDO mapping in PRE-OP is the
  only exception and goes through the implementation's own configuration hook, not through this gate.

Process data is exchanged through two structured NumPy arrays in ring order, ``outputs`` (RxPDO,
master -> drive) and ``inputs`` (TxPDO, drive -> master), laid out exactly as ``drivers/erob/objects.py`` maps them.
"""

from __future__ import annotations

import math
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from humanoid_prime.control.rate import Rate
from humanoid_prime.drivers.erob.constants import MIN_CYCLE_S, MODE_CSP
from humanoid_prime.drivers.erob.objects import RXPDO, TXPDO
from humanoid_prime.drivers.ethercat.errors import RingError, SdoError, SdoRefused
from humanoid_prime.drivers.ethercat.priority import feeding_priority
from humanoid_prime.drivers.ethercat.ring import ExpectedSlave, SlaveInfo, check_ring, describe_states
from humanoid_prime.drivers.ethercat.sdo_client import read_error_history, read_live_error
from humanoid_prime.drivers.ethercat.wire import AL_ERROR, AlState, describe_al_state
from humanoid_prime.errors import PrimeError

RX_DTYPE = np.dtype([(e.name, e.dtype) for e in RXPDO])  # 14 bytes per slave, packed
TX_DTYPE = np.dtype([(e.name, e.dtype) for e in TXPDO])  # 16 bytes per slave, packed
OP_REQUEST_REPEAT_S = 0.5  # a slave left in SAFE-OP after OP was asked for is asked again this often


@dataclass(frozen=True)
class BringupReport:
    """How the ring reached OP: wall time, bring-up cycles, and the rates used."""

    seconds: float
    cycles: int
    bringup_rate: float
    sync0_period_ns: int

    def as_dict(self) -> dict[str, object]:
        return {"seconds": self.seconds, "cycles": self.cycles, "bringup_rate": self.bringup_rate,
                "sync0_period_ns": self.sync0_period_ns}


def sync0_period_ns(update_rate: float, *, sync0_period_s: float | None = None) -> int:
    """The SYNC0 cycle in ns: the loop period, 1/update_rate; an override must equal it.

    The distributed clock is driven by the loop's frames, so SYNC0 and the loop period are one number.
    A SYNC0 faster than the frame rate never locks and the drives fault (statusword 4616, DESIGN §3).
    """
    if isinstance(update_rate, bool) or not isinstance(update_rate, (int, float)) \
            or not math.isfinite(update_rate) or update_rate <= 0:
        raise PrimeError(f"update_rate must be a positive number of Hz, got {update_rate!r}")
    period_ns = round(1e9 / update_rate)
    if period_ns < round(MIN_CYCLE_S * 1e9):
        raise PrimeError(f"update_rate {update_rate:g} Hz gives a {period_ns / 1e3:g} us cycle, below the eRob "
                         f"minimum of {MIN_CYCLE_S * 1e6:g} us; use at most {1 / MIN_CYCLE_S:g} Hz")
    if sync0_period_s is not None:
        requested_ns = round(sync0_period_s * 1e9) if math.isfinite(sync0_period_s) else -1
        if requested_ns != period_ns:
            raise PrimeError(
                f"sync0_period {sync0_period_s * 1e3:g} ms differs from the loop period {period_ns / 1e6:g} ms "
                f"(1/update_rate, {update_rate:g} Hz): the distributed clock is driven by the loop's frames, so "
                "a SYNC0 faster than the frame rate never locks and the drives fault with statusword 4616 "
                "(0x1208), and a slower one skips targets; leave sync0_period unset (it is derived from "
                "update_rate) or change update_rate instead")
    return period_ns


def next_op_requests(states: Sequence[tuple[int, int]], op_asked: npt.NDArray[np.float64],
                     now: float) -> list[tuple[int, int]]:
    """(ring position, AL state) of the slaves the bring-up loop pushes toward OP at ``now``; ``op_asked``
    is updated.

    An error in SAFE-OP is acknowledged at once, and OP is asked for at the next look. A slave in SAFE-OP
    that was asked is asked again only every ``OP_REQUEST_REPEAT_S``: it waits there for its DC lock, and
    every AL control write is a frame round trip the loop's next cycle waits behind. At 1 kHz, asking all
    ten every 10 ms delayed a frame past the drives' sync tolerance each time and restarted their lock.
    """
    push = []
    for k, (state, _) in enumerate(states):
        if state == AlState.SAFE_OP | AL_ERROR:
            op_asked[k] = -math.inf
        elif state == AlState.SAFE_OP and now - op_asked[k] >= OP_REQUEST_REPEAT_S:
            op_asked[k] = now
        else:
            continue
        push.append((k, state))
    return push


class EthercatMaster(ABC):
    """One EtherCAT ring of eRob drives in CSP, addressed by ring position (0 = first after the master)."""

    def __init__(self, interface: str, *, update_rate: float, bringup_rate: float = 1000.0,
                 sync0_period_s: float | None = None, bringup_timeout_s: float = 30.0,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], object] = time.sleep) -> None:
        self.interface = interface
        self.cycle_ns = sync0_period_ns(update_rate, sync0_period_s=sync0_period_s)
        self.sync0_ns = self.cycle_ns  # SYNC0 armed on the slaves: the loop period, always
        self.clock = clock  # paces the bring-up and times its waits (the keeper runs on the wall clock)
        self.sleep = sleep
        if not (math.isfinite(bringup_rate) and bringup_rate > 0):
            raise PrimeError(f"bringup_rate must be a positive number of Hz, got {bringup_rate!r}")
        self.bringup_rate = float(bringup_rate)
        self.bringup_timeout_s = bringup_timeout_s
        self.slaves: tuple[SlaveInfo, ...] = ()
        self.outputs = np.zeros(0, RX_DTYPE)
        self.inputs = np.zeros(0, TX_DTYPE)
        self.wkc = 0
        self.expected_wkc = 0
        self.operational = False  # every slave reached OP at the end of start()
        self.flowing = False  # a full-working-counter exchange happened since then
        # Ring health kept by the implementation's supervision, in ring order.
        self.slave_ok = np.zeros(0, dtype=bool)
        self.left_op = np.zeros(0, dtype=np.int64)  # times the supervision found each slave out of OP since start
        self.left_op_code = np.zeros(0, dtype=np.uint16)  # the AL status code each slave gave when it last left OP
        self.al_state = np.zeros(0, dtype=np.uint16)
        self.al_status_code = np.zeros(0, dtype=np.uint16)
        self.health_version = 0
        self.recovery_problems: dict[int, str] = {}  # ring position -> why its recovery cannot go on (e.g. its clock)
        # Rated torque of each drive (0x6076, read in PRE-OP by implementations that can; NaN = not read), the
        # torque that 0x6077 and 0x60B2 count in per mille; why a drive's could not be read.
        self.rated_torque_nm = np.zeros(0)
        self.rated_torque_problems: dict[int, str] = {}
        self.mailbox = "prime"  # who works the slaves' mailboxes (buses.ethercat.mailbox): Prime's layer, or SOEM's
        self.kept_cycles = 0  # frames the keeper sent while the owner of the cycle was quiet
        self.cycles_answered = 0  # cycle frames that came back answered (each carried the ring's time)
        self._io = threading.Lock()  # one send or receive at a time: the owner's and the keeper's
        self._in_flight = False
        self._last_send = 0.0
        self._kept_last = False  # the keeper, not the owner, sent the last frame
        self._keeper: threading.Thread | None = None
        self._stop_keeping = threading.Event()

    # ------------------------------------------------------------------------------- lifecycle
    def open(self) -> tuple[SlaveInfo, ...]:
        """Open the interface and discover the ring (slaves end in PRE-OP); returns what was found."""
        if not self.slaves:
            self.slaves = tuple(self._discover())
            n = len(self.slaves)
            self.slave_ok = np.zeros(n, dtype=bool)
            self.left_op = np.zeros(n, dtype=np.int64)
            self.left_op_code = np.zeros(n, dtype=np.uint16)
            self.al_state = np.array([s.al_state for s in self.slaves], dtype=np.uint16)
            self.al_status_code = np.array([s.al_status_code for s in self.slaves], dtype=np.uint16)
            self.rated_torque_nm = np.full(n, math.nan)
        return self.slaves

    def store_rated_torque(self, position: int, raw: bytes) -> None:
        """Keep what the drive at ``position`` answered for 0x6076 (UNSIGNED32 mN*m), or why it is unusable."""
        if not 1 <= len(raw) <= 4:
            self.rated_torque_problems[position] = f"0x6076 answered {len(raw)} bytes, expected 4 (UNSIGNED32 mN*m)"
            return
        milli = int.from_bytes(raw, "little")
        if milli == 0:
            self.rated_torque_problems[position] = "0x6076 reads 0 mN*m"
            return
        self.rated_torque_nm[position] = milli / 1000.0
        self.rated_torque_problems.pop(position, None)

    def start(self, expected: Sequence[ExpectedSlave]) -> BringupReport:
        """Check the ring, map the PDOs, configure DC/SYNC0 and bring every slave to OP.

        The bring-up loop runs at ``bringup_rate`` (independent of the control rate) and keeps every
        slave's outputs fed while the others join: each cycle the CSP target follows the actual position
        and the controlword keeps the drive disabled.
        """
        if self.operational:
            raise RingError(f"EtherCAT ring on {self.interface} is already in OP; close the master to start again")
        self.open()
        check_ring(self.slaves, expected, self.interface)
        t0 = self.clock()
        self._configure()
        n = len(self.slaves)
        if self.outputs.shape != (n,) or self.inputs.shape != (n,):
            raise RingError(f"{type(self).__name__} configured {self.outputs.shape} outputs for {n} slaves")
        self.outputs[:] = 0
        self.outputs["mode_of_operation"] = MODE_CSP
        with feeding_priority():
            cycles = self._bring_to_op(t0)
        self.operational = True
        self.slave_ok[:] = True
        self.health_version += 1
        self._started()
        self._stop_keeping.clear()
        self._keeper = threading.Thread(target=self._keep, name=f"ethercat-keep-{self.interface}", daemon=True)
        self._keeper.start()
        return BringupReport(self.clock() - t0, cycles, self.bringup_rate, self.sync0_ns)

    def _bring_to_op(self, t0: float) -> int:
        """The fast loop of ``start`` until every slave is in OP; the cycles it took."""
        n = len(self.slaves)
        deadline = t0 + self.bringup_timeout_s
        check_every = max(1, round(self.bringup_rate * 0.01))  # read AL states about every 10 ms
        cycles = 0
        rate = Rate(self.bringup_rate, clock=self.clock, sleep=self.sleep)
        op_asked = np.full(n, -math.inf)  # when each slave was last asked for OP (-inf: since its last ack)
        while True:
            rate.wait()
            np.copyto(self.outputs["target_position"], self.inputs["position_actual"])
            self.outputs["controlword"] = 0
            wkc = self.exchange()
            cycles += 1
            if cycles == 1:  # one valid frame first, so the outputs are defined when OP is asked for
                self._request_op()
                op_asked[:] = self.clock()
            if wkc == self.expected_wkc or cycles % check_every == 0:
                states = self._read_states()
                self._store_states(states)
                if all(state == AlState.OP for state, _ in states):
                    break
                self._advance(next_op_requests(states, op_asked, self.clock()))
            if self.clock() > deadline:
                raise RingError(self._not_op_message(f"did not reach OP within {self.bringup_timeout_s:g} s"))
        return cycles

    def close(self) -> None:
        """Stop every thread, leave the slaves in INIT and release the interface."""
        self._stop_keeping.set()
        if self._keeper is not None:
            self._keeper.join()
            self._keeper = None
        self.operational = False
        self.flowing = False
        self._close()

    def __enter__(self) -> EthercatMaster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------ cyclic
    def exchange(self) -> int:
        """Send ``outputs`` and receive ``inputs`` in one round trip; returns the working counter."""
        with self._io:
            self._send_now()
            return self._receive_now()

    def send(self) -> None:
        """Send ``outputs`` (non-blocking; the next ``receive`` collects the frame)."""
        with self._io:
            if self._in_flight:  # a frame nobody collected: collect it first, one frame in flight at a time
                self._receive_now()
            self._send_now()

    def receive(self) -> int:
        """Collect the frame in flight into ``inputs`` (sending one first if there is none); returns the WKC."""
        with self._io:
            if not self._in_flight:
                self._send_now()
            return self._receive_now()

    def _send_now(self) -> None:
        self._send()
        self._in_flight = True
        self._last_send = time.monotonic()
        self._kept_last = False

    def _receive_now(self) -> int:
        wkc = self._receive()
        self._in_flight = False
        self.wkc = wkc
        if wkc > 0:
            self.cycles_answered += 1
        if wkc == self.expected_wkc:
            self.flowing = self.operational
        elif self.operational:
            self._wkc_mismatch()
        return wkc

    def refresh(self) -> None:
        """One cycle frame now, between the owner's: a frame in flight is collected first and another sent in its
        place, for the owner to collect."""
        with self._io:
            if self._in_flight:
                self._receive_now()
                self._send_now()
            else:
                self._send_now()
                self._receive_now()

    def _keep(self) -> None:
        """Once in OP, every cycle period: when the owner of the cycle has been quiet for two periods, send the
        current outputs, and go on every period until it ticks again, so no slave's output watchdog runs out
        and SYNC0 keeps its frames while controllers load, a tick stalls, or the component is inactive."""
        with feeding_priority():
            self._keep_feeding()

    def _keep_feeding(self) -> None:
        rate = Rate(1e9 / self.cycle_ns, sleep=self._stop_keeping.wait)
        quiet_s = 2e-9 * self.cycle_ns
        while True:
            rate.wait()
            if self._stop_keeping.is_set():
                return
            with self._io:
                if not self._kept_last and time.monotonic() - self._last_send < quiet_s:
                    continue  # the owner is ticking
                self._send_now()
                self._receive_now()
                self._kept_last = True
                self.kept_cycles += 1

    # ----------------------------------------------------------------------------------- SDO
    @property
    def sdo_ready(self) -> bool:
        """True once every slave is in OP and process data flows. SDOs are refused before; afterwards, while a
        slave recovers, only that slave's."""
        return self.operational and self.flowing and bool(self.slave_ok.all())

    def readiness(self) -> str:
        """Why ``sdo_ready`` is false, in words ('' when it is true): the slaves out of OP, or the working counter."""
        if self.sdo_ready:
            return ""
        if not self.operational:
            return self._not_op_message("is not operational")
        if not self.slave_ok.all():
            return self._not_op_message("has slaves recovering")
        return (f"EtherCAT ring on {self.interface}: process data is not flowing (working counter {self.wkc}, "
                f"expected {self.expected_wkc})")

    def _gate(self, position: int, index: int, sub_index: int) -> None:
        if not 0 <= position < len(self.slaves):
            raise SdoError(position, index, sub_index,
                           f"no slave at that ring position (the ring has {len(self.slaves)} slaves)")
        if self.sdo_ready:
            return
        if self.operational and self.flowing and self.slave_ok[position]:
            return  # another slave is recovering; this one is in OP, its mailbox traffic disturbs no DC lock
        if not self.operational:
            why = "the ring is still being brought up"
        elif not self.slave_ok[position]:
            why = f"ring {position} is not in OP ({describe_al_state(int(self.al_state[position]))})"
        else:
            why = "no process data has flowed yet"
        raise SdoRefused(position, index, sub_index,
                         f"refused: {why}; mailbox traffic before every slave is in OP with joint states flowing "
                         "faults a drive with 0xA000; retry once bring-up has finished")

    def sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        """Upload one object entry from the slave at ``position``.

        Safe to call from several threads at once for different slaves while the cycle runs. Before the
        ring is in OP with process data flowing it raises SdoRefused.
        """
        self._gate(position, index, sub_index)
        return self._sdo_read(position, index, sub_index)

    def sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        """Download ``data`` (little-endian bytes) to one object entry; same rules as ``sdo_read``."""
        self._gate(position, index, sub_index)
        self._sdo_write(position, index, sub_index, bytes(data))

    def mailbox_drops(self) -> dict[str, int]:
        """The mailbox messages dropped so far, by why (``coe.DROP_REASONS``; empty where none are counted)."""
        return {}

    def mailbox_given_up(self) -> int:
        """Requests whose reply the mailboxes gave up on (asked again, or timed out; 0 where none are counted)."""
        return 0

    def live_error(self, position: int) -> int:
        return read_live_error(self, position)

    def error_history(self, position: int) -> list[int]:
        return read_error_history(self, position)

    # ----------------------------------------------------------------------------- states
    def read_states(self) -> tuple[SlaveInfo, ...]:
        """Fresh AL state and AL status code of every slave (a frame round trip; not for the hot path)."""
        states = self._read_states()
        self._store_states(states)
        self.slaves = tuple(
            SlaveInfo(s.position, s.name, s.vendor_id, s.product_code, s.revision, state, code)
            for s, (state, code) in zip(self.slaves, states, strict=True))
        return self.slaves

    def _store_states(self, states: Sequence[tuple[int, int]]) -> None:
        for k, (state, code) in enumerate(states):
            self.al_state[k] = state
            self.al_status_code[k] = code

    def _not_op_message(self, what: str, want: int = AlState.OP) -> str:
        current = [SlaveInfo(s.position, s.name, s.vendor_id, s.product_code, s.revision, int(self.al_state[k]),
                             int(self.al_status_code[k])) for k, s in enumerate(self.slaves)]
        return (f"EtherCAT ring on {self.interface} {what}: {describe_states(current, want)}; "
                f"SYNC0 {self.sync0_ns / 1e6:g} ms, bring-up loop {self.bringup_rate:g} Hz")

    # ------------------------------------------------------------------ implementation hooks
    @abstractmethod
    def _discover(self) -> Sequence[SlaveInfo]:
        """Open the interface and enumerate the slaves (ring order)."""

    @abstractmethod
    def _configure(self) -> None:
        """Map the PDOs in PRE-OP, configure DC and SYNC0 (``sync0_ns``), reach SAFE-OP.

        Sizes ``outputs``/``inputs`` to one entry per slave and sets ``expected_wkc``.
        """

    @abstractmethod
    def _request_op(self) -> None:
        """Ask every slave for OP (non-blocking)."""

    @abstractmethod
    def _read_states(self) -> list[tuple[int, int]]:
        """(AL state, AL status code) of every slave, ring order."""

    @abstractmethod
    def _advance(self, slaves: Sequence[tuple[int, int]]) -> None:
        """One step toward OP for each (ring position, AL state) given: acknowledge an error in SAFE-OP, else
        request OP."""

    def _started(self) -> None:
        """Called once every slave is in OP (e.g. to start ring supervision)."""

    @abstractmethod
    def _send(self) -> None:
        """Put ``outputs`` on the wire (non-blocking)."""

    @abstractmethod
    def _receive(self) -> int:
        """Collect the frame sent last into ``inputs``; the working counter (<= 0 when it did not return)."""

    def _wkc_mismatch(self) -> None:
        """Called from the cycle on a working-counter mismatch in OP (e.g. to wake ring supervision)."""

    @abstractmethod
    def _sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        """Blocking upload; raise SdoError on failure."""

    @abstractmethod
    def _sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        """Blocking download; raise SdoError on failure."""

    @abstractmethod
    def _close(self) -> None:
        """Leave the slaves in INIT and release the interface."""
