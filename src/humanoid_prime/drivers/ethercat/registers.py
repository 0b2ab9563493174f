"""Register access to the slaves of one ring over Prime's own frames (``link.py``): one channel per slave (its
register reads and writes and its mailbox, one exchange at a time) and one for the whole ring (AL states).

SOEM gives slave ``k`` (ring position, 0-based) the station address ``0x1001 + k`` (``EC_NODEOFFSET`` + its
1-based number, ecx_config_init); ``check_stations`` confirms that before anything is sent to those addresses.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Sequence

from humanoid_prime.drivers.ethercat.link import (
    FIRST_INDEX,
    LAST_INDEX,
    Channel,
    LateReply,
    Reply,
    Request,
    Wire,
    aprd,
    apwr,
    brd,
    fprd,
    fpwr,
    index_ranges,
)
from humanoid_prime.drivers.ethercat.wire import (
    AL_ERROR,
    AL_STATE_MASK,
    EEPROM_BUSY,
    EEPROM_COMMAND_READ,
    EEPROM_COMMAND_SHIFT,
    EEPROM_TO_PDI,
    REG_AL_CONTROL,
    REG_AL_STATUS,
    REG_EEPROM_CONFIG,
    REG_EEPROM_CONTROL,
    REG_EEPROM_DATA,
    REG_STATION_ADDRESS,
    SII_IDENTITY,
    AlState,
    Command,
)

STATION_BASE = 0x1001
REGISTER_TIMEOUT_S = 0.05  # a register frame: microseconds on a ring, tens of ms behind a stalled host
_EEPROM_READ = struct.Struct("<HI")  # 0x0502 control, 0x0504 word address
_AL_STATUS = struct.Struct("<HxxH")  # 0x0130 status, reserved, 0x0134 AL status code
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
MAX_CHANNELS = (LAST_INDEX - FIRST_INDEX + 1) // 2


class NoReply(Exception):
    """A register frame got no reply in time, or a slave did not answer its datagram (working counter 0)."""

    def __init__(self, what: str) -> None:
        super().__init__(what)
        self.what = what


class RingRegisters:
    """The ring's slaves by ring position, over channels whose wires ``make_wire`` opens (one per index range)."""

    def __init__(self, make_wire: Callable[[range], Wire], slaves: int, *,
                 clock: Callable[[], float] = time.monotonic, on_sent: Callable[[], None] | None = None) -> None:
        self.slaves = slaves
        self.clock = clock
        ranges = index_ranges(min(slaves, MAX_CHANNELS - 1) + 1)
        self.ring = Channel(make_wire(ranges[0]), ranges[0], clock=clock, on_sent=on_sent)
        self._channels = [Channel(make_wire(r), r, clock=clock, on_sent=on_sent) for r in ranges[1:]]
        self.stations = [STATION_BASE + k for k in range(slaves)]

    def channel(self, k: int) -> Channel:
        """Slave ``k``'s channel (shared with others only on rings of more than ``MAX_CHANNELS - 1`` slaves)."""
        return self._channels[k % len(self._channels)]

    # ------------------------------------------------------------------------------------------ one slave
    def read(self, k: int, address: int, size: int, timeout_s: float = REGISTER_TIMEOUT_S) -> bytes:
        """``size`` bytes at ``address`` of slave ``k``; NoReply when the frame or the slave did not answer."""
        replies = self.channel(k).exchange([fprd(self.stations[k], address, size)], timeout_s=timeout_s)
        if replies is None or replies[0].wkc != 1:
            raise NoReply(f"ring {k}: register 0x{address:04X} " + ("not answered" if replies else "no reply frame"))
        return replies[0].data

    def read_agreed(self, k: int, address: int, size: int, timeout_s: float = REGISTER_TIMEOUT_S,
                    attempts: int = 4) -> bytes:
        """Registers that do not change, read until two reads in a row agree (a slave or a frame that answers
        with something else once is not believed)."""
        last = None
        for _ in range(attempts):
            data = self.read(k, address, size, timeout_s)
            if data == last:
                return data
            last = data
        raise NoReply(f"ring {k}: registers 0x{address:04X}-0x{address + size - 1:04X} read differently each time")

    def write(self, k: int, address: int, data: bytes, timeout_s: float = REGISTER_TIMEOUT_S) -> None:
        replies = self.channel(k).exchange([fpwr(self.stations[k], address, data)], timeout_s=timeout_s)
        if replies is None or replies[0].wkc != 1:
            raise NoReply(f"ring {k}: register 0x{address:04X} " + ("not written" if replies else "no reply frame"))

    def sii_read(self, k: int, word: int, timeout_s: float = 0.02) -> int:
        """Word ``word`` (and the next) of slave ``k``'s SII EEPROM, as a u32, through its EEPROM interface."""
        self.write(k, REG_EEPROM_CONTROL, _EEPROM_READ.pack(EEPROM_COMMAND_READ << EEPROM_COMMAND_SHIFT, word))
        deadline = self.clock() + timeout_s
        while _U16.unpack(self.read(k, REG_EEPROM_CONTROL, 2))[0] & EEPROM_BUSY:
            if self.clock() > deadline:
                raise NoReply(f"ring {k}: its EEPROM stayed busy")
        data: int = _U32.unpack(self.read(k, REG_EEPROM_DATA, 4))[0]
        return data

    def sii_identity(self, k: int) -> tuple[int, int, int]:
        """(vendor, product code, revision) as slave ``k``'s SII holds them, read over our frames; the EEPROM goes back
        to the slave's firmware afterwards if it had it (a slave needs it in INIT -> PRE-OP)."""
        pdi = self.read(k, REG_EEPROM_CONFIG, 1)[0] & EEPROM_TO_PDI
        if pdi:
            self.write(k, REG_EEPROM_CONFIG, b"\x00")
        try:
            vendor, product, revision = (self.sii_read(k, word) for word in SII_IDENTITY)
            return vendor, product, revision
        finally:
            if pdi:
                self.write(k, REG_EEPROM_CONFIG, bytes((EEPROM_TO_PDI,)))

    def readdress(self, k: int, identity: tuple[int, int, int]) -> bool:
        """Slave ``k`` answers at its station address again: True at once if it does; one that answers at its
        ring position without an address (back from a power cycle, in INIT) gets it back when its SII says it is
        the same device (vendor, product, revision), as SOEM's ``ecx_recover_slave`` does, one frame at a time."""
        replies = self.ring.exchange([aprd(k, REG_STATION_ADDRESS, 2)], timeout_s=REGISTER_TIMEOUT_S)
        if replies is None or replies[0].wkc != 1:
            return False
        address: int = _U16.unpack(replies[0].data)[0]
        if address == self.stations[k] or address != 0:
            return address == self.stations[k]  # another address is another slave's to keep
        self.ring.exchange([apwr(k, REG_STATION_ADDRESS, _U16.pack(self.stations[k]))], timeout_s=REGISTER_TIMEOUT_S)
        try:
            found: tuple[int, ...] | None = self.sii_identity(k)
        except NoReply:
            found = None
        if found == tuple(identity):
            return True
        self.ring.exchange([apwr(k, REG_STATION_ADDRESS, _U16.pack(0))], timeout_s=REGISTER_TIMEOUT_S)
        return False

    def request_state(self, k: int, state: int) -> None:
        """Write AL control of slave ``k`` (``state``, with the acknowledge bit if asked)."""
        self.write(k, REG_AL_CONTROL, _U16.pack(state))

    # ---------------------------------------------------------------------------------------- whole ring
    def count(self, timeout_s: float) -> int | None:
        """How many slaves answer a broadcast read (None: the frame did not come back in ``timeout_s``)."""
        replies = self.ring.exchange([brd(0x0000, 1)], timeout_s=timeout_s)
        return None if replies is None else replies[0].wkc

    def check_stations(self, timeout_s: float = REGISTER_TIMEOUT_S) -> list[int]:
        """Ring positions whose station address is not the one SOEM gives (read by position)."""
        requests = [aprd(k, REG_STATION_ADDRESS, 2) for k in range(self.slaves)]
        replies = self._exchange_all(requests, timeout_s)
        return [k for k, reply in enumerate(replies or [])
                if reply.wkc != 1 or _U16.unpack(reply.data)[0] != self.stations[k]] if replies else \
            list(range(self.slaves))

    def states(self, timeout_s: float = REGISTER_TIMEOUT_S) -> list[tuple[int, int] | None] | None:
        """(AL state with error flag, AL status code) of every slave, None for one that did not answer; None
        altogether when no reply came. One broadcast read first, as SOEM's ``ecx_readstate`` does: when every
        slave answers it with the same state and no error, that is every slave's state; else each is read."""
        replies = self.ring.exchange([brd(REG_AL_STATUS, 2)], timeout_s=timeout_s)
        if replies is None:
            return None
        together = _U16.unpack(replies[0].data)[0]
        if replies[0].wkc == self.slaves and together in (AlState.INIT, AlState.PRE_OP, AlState.SAFE_OP, AlState.OP):
            return [(together, 0)] * self.slaves
        requests = [fprd(station, REG_AL_STATUS, _AL_STATUS.size) for station in self.stations]
        replies = self._exchange_all(requests, timeout_s)
        if replies is None:
            return None
        return [_al_status(r.data) if r.wkc == 1 else None for r in replies]

    def request_all(self, state: int) -> int:
        """Write AL control of every slave in one broadcast; how many took it (0 when the frame was lost)."""
        replies = self.ring.exchange([Request(Command.BWR, 0, REG_AL_CONTROL, data=_U16.pack(state))],
                                     timeout_s=REGISTER_TIMEOUT_S)
        return 0 if replies is None else replies[0].wkc

    def _exchange_all(self, requests: Sequence[Request], timeout_s: float) -> list[Reply] | None:
        """``requests`` in as few frames as fit (a frame carries at most 1486 bytes of datagrams)."""
        replies: list[Reply] = []
        batch: list[Request] = []
        size = 0
        for request in [*requests, None]:
            if request is None or size + 12 + request.length > 1400:
                if batch:
                    got = self.ring.exchange(batch, timeout_s=timeout_s)
                    if got is None:
                        return None
                    replies += got
                batch, size = [], 0
            if request is not None:
                batch.append(request)
                size += 12 + request.length
        return replies

    # ------------------------------------------------------------------------------------------ lateness
    def frames_lost(self) -> int:
        """Frames that did not come back in time, over every channel (sent again, or their exchange given up)."""
        return sum(channel.resent + channel.unanswered for channel in (self.ring, *self._channels))

    def late_since(self, since: float) -> list[LateReply]:
        """Replies that came after their frame was given up on, since ``since``, over every channel."""
        return sorted((late for channel in (self.ring, *self._channels) for late in channel.late_since(since)),
                      key=lambda late: late.at)

    def close(self) -> None:
        for channel in (self.ring, *self._channels):
            channel.close()


def _al_status(data: bytes) -> tuple[int, int]:
    """(AL state with its error indication, AL status code) from 0x0130-0x0135."""
    status, code = _AL_STATUS.unpack(data)
    return status & (AL_ERROR | AL_STATE_MASK), code
