"""A test double of pysoem's ``Master`` for SoemMaster: eRob slaves with an object dictionary, no network.

It keeps pysoem's contracts that SoemMaster relies on: ``config_map`` calls each slave's ``config_func``
with its 0-based position and re-raises the first exception one raised; a slave maps whatever 0x1600/0x1A00
hold (ZeroErr's power-up layout until a master remaps it); ``read_state`` leaves a state of NONE where a
slave did not answer; transfers raise pysoem's own exception classes. Faults are scripted per transfer
(``fail``) and per state read (``lose_state_reads``: the next N reads lost; ``state_read_losses``: one
True or False per read to come, before those); ``clock`` is advanced by a mailbox timeout instead of waiting
one out. A slave's ESC registers are reached with pysoem's ``_fprd``/``_fpwr`` (AL control and status, the
SyncManagers and FMMUs as config_map leaves them); a state requested through AL control shows after
``state_change_reads`` reads of the AL status, and the register writes are logged in ``register_writes``.
With ``dc`` the slaves have distributed clocks: a local time (``local_ns``, fixed: no time passes), the offset
and delay registers, and 0x092C as the reference clock's (slave 0's) system time minus its own, or
``clock_error_ns`` whatever the offset (a clock that will not come into step); ``Master.dc_time`` moves on each
read, as it does with every cycle.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

import pysoem

from humanoid_prime.drivers.erob.constants import PRODUCT_CODE, VENDOR_ID
from humanoid_prime.drivers.erob.objects import POWER_UP_RXPDO, POWER_UP_TXPDO, RATED_TORQUE

# What config_map leaves in an eRob's ESC: 4 SyncManagers (mailbox out/in, outputs, inputs), 2 FMMUs in use of 3
ESC_SYNC_MANAGERS = (struct.pack("<HHBBBB", 0x1000, 128, 0x26, 0x01, 0x01, 0x00),
                     struct.pack("<HHBBBB", 0x1080, 128, 0x22, 0x08, 0x03, 0x01),  # status, repeat, PDI set by it
                     struct.pack("<HHBBBB", 0x1100, 13, 0x64, 0x00, 0x01, 0x00),
                     struct.pack("<HHBBBB", 0x1400, 15, 0x20, 0x00, 0x01, 0x00))
ESC_FMMUS = (struct.pack("<IHBBHBBBxxx", 0x0000, 13, 0, 7, 0x1100, 0, 2, 1),
             struct.pack("<IHBBHBBBxxx", 0x0100, 15, 0, 7, 0x1400, 0, 1, 1),
             bytes(16))

NO_REPLY = "no reply"  # a scripted failure: the mailbox timeout runs out
LOST_FRAME = "lost frame"  # a scripted failure: the working counter comes back 0 at once
RING_TIME_NS = 816_000_000_000_000_000  # the reference clock's system time (ns since 2000)


class Clock:
    """Seconds that move only when told (the double's mailbox timeouts advance it)."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class FakeSoemSlave:
    def __init__(self, master: FakeSoemMaster, position: int, rated_torque_mnm: int) -> None:
        self._master = master
        self.position = position
        self.name, self.man, self.id, self.rev = "eRob", VENDOR_ID, PRODUCT_CODE, 1
        self.state, self.al_status = pysoem.NONE_STATE, 0
        self.true_state = pysoem.PREOP_STATE
        self.answering = True
        self.config_func: Callable[[int], None] | None = None
        self.output, self.input = b"", b""
        self.objects: dict[tuple[int, int], bytes] = {(RATED_TORQUE, 0): struct.pack("<I", rated_torque_mnm)}
        for mapping, entries in ((0x1600, POWER_UP_RXPDO), (0x1A00, POWER_UP_TXPDO)):
            self.objects[(mapping, 0)] = bytes([len(entries)])
            for sub, entry in enumerate(entries, start=1):
                self.objects[(mapping, sub)] = struct.pack("<I", entry.mapping)
        self.writes: list[tuple[int, int, bytes]] = []
        self.dc = False
        self.registers = bytearray(0x1000)
        self.registers[0x0004:0x0006] = bytes((len(ESC_FMMUS), 8))
        for n, data in enumerate(ESC_SYNC_MANAGERS):
            self.registers[0x0800 + 8 * n:0x0808 + 8 * n] = data
        for n, data in enumerate(ESC_FMMUS):
            self.registers[0x0600 + 16 * n:0x0610 + 16 * n] = data
        self.register_writes: list[tuple[int, bytes]] = []
        self.local_ns = RING_TIME_NS + 1_000 * position
        self.clock_error_ns = 0
        self.difference_reversed = False  # bit 31 of 0x092C the other way round
        if master.dc:
            self.registers[0x0008] = 0x04  # ESC features: DC
            struct.pack_into("<QI", self.registers, 0x0920, (-1_000 * position) % (1 << 64), 700 * position)
            struct.pack_into("<H", self.registers, 0x0930, 0x1000)
        self.state_change_reads = 0
        self.status_reads = 0
        self._change: list[int] = []  # [requested state, AL status reads left]

    def add_emergency_callback(self, callback: Callable) -> None:
        pass

    def _scripted(self, index: int, sub: int) -> None:
        failures = self._master.failures.get((self.position, index, sub))
        if not failures:
            return
        failure = failures.pop(0)
        if failure == NO_REPLY:
            self._master.clock.now += self._master.sdo_read_timeout / 1e6
            raise pysoem.WkcError(message="no reply", wkc=0)
        if failure == LOST_FRAME:
            raise pysoem.WkcError(message="lost frame", wkc=0)
        raise pysoem.SdoError(self.position + 1, index, sub, failure, "scripted abort")

    def sdo_read(self, index: int, sub: int, size: int = 256, release_gil: bool = False) -> bytes:
        self._scripted(index, sub)
        if (index, sub) not in self.objects:
            raise pysoem.SdoError(self.position + 1, index, sub, 0x06020000, "Object does not exist")
        return self.objects[(index, sub)]

    def sdo_write(self, index: int, sub: int, data: bytes, ca: bool = False, release_gil: bool = False) -> None:
        self._scripted(index, sub)
        self.objects[(index, sub)] = bytes(data)
        self.writes.append((index, sub, bytes(data)))

    def mapped_bytes(self, mapping: int) -> int:
        count = self.objects[(mapping, 0)][0]
        return sum(struct.unpack("<I", self.objects[(mapping, sub)])[0] & 0xFF for sub in range(1, count + 1)) // 8

    def dc_sync(self, act: bool, sync0_cycle_time: int, sync0_shift_time: int = 0, sync1_cycle_time=None) -> None:
        self.dc = act

    def write_state(self) -> int:
        requested = self.state & 0x0F
        if requested in (pysoem.SAFEOP_STATE, pysoem.OP_STATE):
            self.true_state = requested
        return 1

    def _fprd(self, address: int, size: int, timeout_us: int = 2000) -> bytes:
        if not self.answering:
            raise pysoem.WkcError()
        if address == 0x0130 and self._change:
            self._change[1] -= 1
            if self._change[1] <= 0:
                self.true_state, self._change = self._change[0], []
        if address == 0x0130:
            self.status_reads += 1
            struct.pack_into("<H", self.registers, 0x0130, self.true_state)
        if address <= 0x0910 < address + size:
            struct.pack_into("<Q", self.registers, 0x0910, self.system_time())
        if address <= 0x092C < address + size:
            difference = self.clock_error_ns or self._master.slaves[0].system_time() - self.system_time()
            magnitude = min(abs(difference), 0x7FFFFFFF)
            behind = difference > 0 if not self.difference_reversed else difference < 0
            struct.pack_into("<I", self.registers, 0x092C, magnitude | (0x80000000 if behind else 0))
        return bytes(self.registers[address:address + size])

    def system_time(self) -> int:
        return (self.local_ns + struct.unpack_from("<Q", self.registers, 0x0920)[0]) % (1 << 64)

    def _fpwr(self, address: int, data: bytes, timeout_us: int = 2000) -> None:
        if not self.answering:
            raise pysoem.WkcError()
        self.registers[address:address + len(data)] = data
        self.register_writes.append((address, bytes(data)))
        if address == 0x0120:
            requested = data[0] & 0x0F
            if self.state_change_reads:
                self._change = [requested, self.state_change_reads]
            else:
                self.true_state = requested

    def recover(self, timeout: int = 500) -> int:
        return 1 if self.answering else 0


class FakeSoemMaster:
    """Stands in for ``pysoem.Master``; ``FakeSoemMaster.ring`` configures the next one created."""

    ring: dict = {}

    def __init__(self) -> None:
        options = dict(FakeSoemMaster.ring)
        self.clock: Clock = options.get("clock") or Clock()
        self.failures: dict[tuple[int, int, int], list] = options.get("failures", {})
        self.lose_state_reads = options.get("lose_state_reads", 0)
        self.state_read_losses: list[bool] = []
        self._rated = options.get("rated_torque_mnm", [23000] * options.get("slaves", 10))
        self.dc = options.get("dc", False)
        self._dc_time = RING_TIME_NS
        self.slaves: list[FakeSoemSlave] = []
        self.sdo_read_timeout = self.sdo_write_timeout = 700_000
        self.manual_state_change = 0
        self.state = pysoem.NONE_STATE
        self.expected_wkc = 0
        self.state_reads = 0
        FakeSoemMaster.last = self

    def open(self, ifname: str, ifname_red: str | None = None) -> None:
        self.ifname = ifname

    def close(self) -> None:
        pass

    def config_init(self, usetable: bool = False) -> int:
        self.slaves = [FakeSoemSlave(self, k, milli) for k, milli in enumerate(self._rated)]
        return len(self.slaves)

    def state_check(self, expected_state: int, timeout: int = 50000) -> int:
        self.read_state()
        return min(slave.state for slave in self.slaves)

    def read_state(self) -> int:
        self.state_reads += 1
        if self.state_read_losses:
            lost = self.state_read_losses.pop(0)
        else:
            lost = self.lose_state_reads > 0
            self.lose_state_reads -= lost
        for slave in self.slaves:
            slave.state = pysoem.NONE_STATE if lost or not slave.answering else slave.true_state
        return min(slave.state for slave in self.slaves)

    def config_map(self) -> int:
        for slave in self.slaves:
            if slave.config_func is not None:
                slave.config_func(slave.position)  # pysoem re-raises what the hook raised
        for slave in self.slaves:
            slave.output = bytes(slave.mapped_bytes(0x1600))
            slave.input = bytes(slave.mapped_bytes(0x1A00))
        self.expected_wkc = 3 * len(self.slaves)
        return sum(len(s.output) + len(s.input) for s in self.slaves)

    def config_dc(self) -> bool:
        return True

    def write_state(self) -> int:
        for slave in self.slaves:
            slave.state = self.state
            slave.write_state()
        return len(self.slaves)

    def send_processdata(self) -> int:
        return 1

    @property
    def dc_time(self) -> int:
        self._dc_time += 10_000_000
        return self._dc_time

    def receive_processdata(self, timeout: int = 2000, release_gil: bool = False) -> int:
        return self.expected_wkc if all(s.answering for s in self.slaves) else self.expected_wkc - 3
