"""Register frames of Prime's own on the ring's NIC, beside SOEM's, each reply matched to its request.

Why not SOEM's: SOEM files a reply by the index of its frame buffer alone, one of the 16 it cycles through
(``ecx_inframe``, oshw/linux/nicdrv.c), and checks nothing else. A frame that comes back after SOEM gave up on it
(``EC_TIMEOUTRET``, 2 ms) is taken as the reply to whichever later datagram holds that index by then: a late
mailbox reply read as SM1's status sends ``ecx_mbxreceive`` down its "repeat request" path, which writes that
stale word back to 0x080D-0x080E with the mailbox's enable bit cleared, and the slave drops to INIT (AL status
0x0016). pysoem's own register access (``_fprd``/``_fpwr``) goes the same way and holds the interpreter lock for
the frame. This belongs fixed in SOEM's frame layer; until it is, Prime sends its register and mailbox frames
here instead.

The split of frame indices: SOEM's are 0..15 (``EC_MAXBUF``), Prime's ``FIRST_INDEX``..0xFF, and each drops the
other's replies (``soem_contract.py`` says what that rests on and checks it). Each ``Channel`` owns a range of
Prime's indices and its own raw socket, whose kernel filter passes only replies in that range: no other thread's
reply is ever read. A reply is taken only if its index is outstanding and every datagram's command, address and
length are the request's. An index whose reply did not come in time is not used again until that late reply has
come (it is counted, with how late it was) or ``QUARANTINE_S`` has passed. Waiting releases the interpreter lock.
``on_sent`` is told of every frame a channel sends (SOEM's socket gets a copy of its reply).

The socket is one implementation of ``Wire``; the test doubles pass the same frames through the emulated ring
in-process.
"""

from __future__ import annotations

import collections
import ctypes
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from humanoid_prime.drivers.ethercat.wire import (
    BROADCAST_MAC,
    DATAGRAM_HEADER,
    DATAGRAM_HEADER_SIZE,
    ECAT_HEADER_SIZE,
    ETH_HEADER_SIZE,
    ETHERTYPE,
    FIRST_INDEX_OFFSET,
    FRAME_TYPE_COMMANDS,
    LENGTH_MASK,
    MASTER_MAC,
    MORE_FOLLOWS,
    WKC_SIZE,
    Command,
)

FIRST_INDEX = 0x40  # our datagram indices: FIRST_INDEX..0xFF; SOEM cycles through 0..15
LAST_INDEX = 0xFF
RETRY_S = 0.002  # a frame not back by then is sent again under a new index (SOEM's EC_TIMEOUTRET)
QUARANTINE_S = 0.25  # an index whose reply never came is used again after this (a stalled host holds frames < 0.1 s)
LATE_KEPT = 64  # late replies remembered (when, how late, what)

_AUTO_OR_BROADCAST = {Command.APRD, Command.APWR, Command.BRD, Command.BWR}  # slaves change ADP on the way
_READS = {Command.APRD, Command.FPRD, Command.BRD}
_ETH = BROADCAST_MAC + MASTER_MAC + struct.pack(">H", ETHERTYPE)  # as SOEM addresses its frames
_ETHERTYPE_BYTES = struct.pack(">H", ETHERTYPE)
_U16 = struct.Struct("<H")


@dataclass(frozen=True)
class Request:
    """One datagram: ``data`` is written by a write command; a read command reads ``size`` bytes."""

    command: int
    adp: int
    ado: int
    data: bytes = b""
    size: int = 0

    @property
    def length(self) -> int:
        return len(self.data) if self.command not in _READS else self.size


@dataclass(frozen=True)
class Reply:
    data: bytes
    wkc: int


@dataclass(frozen=True)
class LateReply:
    at: float  # when it came (the channel's clock)
    late_s: float  # how long after its request
    what: str  # the request, in words


def fprd(station: int, address: int, size: int) -> Request:
    return Request(Command.FPRD, station, address, size=size)


def fpwr(station: int, address: int, data: bytes) -> Request:
    return Request(Command.FPWR, station, address, data=bytes(data))


def aprd(position: int, address: int, size: int) -> Request:
    return Request(Command.APRD, (-position) & 0xFFFF, address, size=size)


def apwr(position: int, address: int, data: bytes) -> Request:
    return Request(Command.APWR, (-position) & 0xFFFF, address, data=bytes(data))


def brd(address: int, size: int) -> Request:
    return Request(Command.BRD, 0, address, size=size)


def build_frame(index: int, requests: Sequence[Request]) -> bytes:
    body = bytearray()
    for k, request in enumerate(requests):
        more = MORE_FOLLOWS if k < len(requests) - 1 else 0
        body += DATAGRAM_HEADER.pack(request.command, index, request.adp, request.ado, request.length | more, 0)
        body += request.data if request.command not in _READS else bytes(request.size)
        body += b"\x00\x00"
    return _ETH + _U16.pack(FRAME_TYPE_COMMANDS << 12 | len(body)) + bytes(body)


def parse_reply(frame: bytes, requests: Sequence[Request]) -> tuple[int, list[Reply]] | None:
    """(index, replies) when ``frame`` has exactly the datagrams of ``requests`` (same command, address and length
    each, same index throughout); None otherwise."""
    if len(frame) < ETH_HEADER_SIZE + ECAT_HEADER_SIZE or frame[12:14] != _ETHERTYPE_BYTES:
        return None
    offset, index, replies = ETH_HEADER_SIZE + ECAT_HEADER_SIZE, None, []
    for k, request in enumerate(requests):
        if offset + DATAGRAM_HEADER_SIZE + WKC_SIZE > len(frame):
            return None
        command, dg_index, adp, ado, length_field, _irq = DATAGRAM_HEADER.unpack_from(frame, offset)
        length = length_field & LENGTH_MASK
        more = bool(length_field & MORE_FOLLOWS)
        if (command != request.command or ado != request.ado or length != request.length
                or (request.command not in _AUTO_OR_BROADCAST and adp != request.adp)
                or more != (k < len(requests) - 1) or index not in (None, dg_index)
                or offset + DATAGRAM_HEADER_SIZE + length + WKC_SIZE > len(frame)):
            return None
        index = dg_index
        data_at = offset + DATAGRAM_HEADER_SIZE
        replies.append(Reply(bytes(frame[data_at:data_at + length]), _U16.unpack_from(frame, data_at + length)[0]))
        offset = data_at + length + WKC_SIZE
    return (index if index is not None else -1), replies


def frame_index(frame: bytes) -> int | None:
    """The index of a frame's first datagram (None for a frame too short to say)."""
    return frame[FIRST_INDEX_OFFSET] if len(frame) > FIRST_INDEX_OFFSET else None


class Wire(Protocol):
    """Where a channel's frames go: ``send`` one frame; ``receive`` the next frame for this channel's indices,
    waiting at most ``timeout_s`` (None when none came). ``receive`` may return frames of other indices too
    (the channel drops them)."""

    def send(self, frame: bytes) -> None: ...

    def receive(self, timeout_s: float) -> bytes | None: ...

    def close(self) -> None: ...


class Channel:
    """Request/reply exchanges over ``wire`` with datagram indices ``indices``, one exchange at a time."""

    def __init__(self, wire: Wire, indices: Sequence[int], *, clock: Callable[[], float] = time.monotonic,
                 retry_s: float = RETRY_S, quarantine_s: float = QUARANTINE_S,
                 on_sent: Callable[[], None] | None = None) -> None:
        if len(indices) < 2:
            raise ValueError(f"a channel needs at least 2 datagram indices, got {len(indices)}")
        self.wire = wire
        self.indices = tuple(indices)
        self.clock = clock
        self.retry_s = retry_s
        self.quarantine_s = quarantine_s
        self.on_sent = on_sent
        self.exchanges = 0
        self.resent = 0  # frames sent again because the first was not back within ``retry_s``
        self.unanswered = 0  # exchanges that got no reply at all in their time
        self.late: collections.deque[LateReply] = collections.deque(maxlen=LATE_KEPT)
        self.late_count = 0
        # index -> (sent at, what, the requests): reply not seen yet
        self._outstanding: dict[int, tuple[float, str, Sequence[Request]]] = {}
        self._next = 0
        self._lock = threading.Lock()

    def exchange(self, requests: Sequence[Request], *, timeout_s: float, repeat: bool = True) -> list[Reply] | None:
        """Send ``requests`` in one frame and return their replies, or None when no matching reply came within
        ``timeout_s``. With ``repeat`` (requests that may be carried out twice: reads that change nothing,
        writes of a value) the frame is sent again under a new index every ``retry_s`` meanwhile, and the reply
        to any of the copies is taken."""
        what = ", ".join(f"{Command(r.command).name} 0x{r.adp:04X}:0x{r.ado:04X}" for r in requests)
        with self._lock:
            self.exchanges += 1
            deadline = self.clock() + timeout_s
            mine: set[int] = set()
            resend_at = deadline
            while True:
                now = self.clock()
                if not mine or (repeat and now >= resend_at and now < deadline):
                    index = self._take_index(deadline)
                    if index is None:
                        break
                    if mine:
                        self.resent += 1
                    mine.add(index)
                    self._outstanding[index] = (self.clock(), what, requests)
                    if self.on_sent is not None:
                        self.on_sent()
                    self.wire.send(build_frame(index, requests))
                    resend_at = self.clock() + self.retry_s
                now = self.clock()
                if now >= deadline:
                    break
                frame = self.wire.receive(min(deadline, resend_at if repeat else deadline) - now)
                if frame is None:
                    continue
                index = frame_index(frame)
                if index in mine:
                    parsed = parse_reply(frame, requests)
                    if parsed is not None:
                        del self._outstanding[index]
                        return parsed[1]
                else:
                    self._file_late(frame)
            self.unanswered += 1
            return None

    def _take_index(self, deadline: float) -> int | None:
        """A free index; while all are outstanding, late replies are awaited (and the oldest index freed after
        ``quarantine_s``). None when ``deadline`` passed first."""
        while True:
            for step in range(len(self.indices)):
                index = self.indices[(self._next + step) % len(self.indices)]
                if index not in self._outstanding:
                    self._next = (self._next + step + 1) % len(self.indices)
                    return index
            now = self.clock()
            oldest, (sent, _what, _requests) = min(self._outstanding.items(), key=lambda item: item[1][0])
            if now - sent >= self.quarantine_s:
                del self._outstanding[oldest]
                continue
            if now >= deadline:
                return None
            frame = self.wire.receive(min(deadline, sent + self.quarantine_s) - now)
            if frame is not None:
                self._file_late(frame)

    def _file_late(self, frame: bytes) -> None:
        """A reply to a request given up on earlier: its index is free again (junk with that index is not)."""
        index = frame_index(frame)
        if index is None:
            return
        outstanding = self._outstanding.get(index)
        if outstanding is None or parse_reply(frame, outstanding[2]) is None:
            return
        del self._outstanding[index]
        sent, what, _requests = outstanding
        now = self.clock()
        self.late.append(LateReply(now, now - sent, what))
        self.late_count += 1

    def late_since(self, since: float) -> list[LateReply]:
        """Late replies that came after ``since`` (the channel's clock)."""
        return [late for late in list(self.late) if late.at >= since]

    def close(self) -> None:
        self.wire.close()


# ---------------------------------------------------------------------------------------------- the raw socket
SO_ATTACH_FILTER = 26
_FILTER = struct.Struct("HBBI")  # struct sock_filter: code, jt, jf, k
# classic BPF opcodes
_LDH_ABS, _LDB_ABS, _JEQ, _JGE, _JGT, _RET = 0x28, 0x30, 0x15, 0x35, 0x25, 0x06


def index_filter(first: int, last: int) -> bytes:
    """A socket filter passing EtherCAT frames whose first datagram's index is in ``first..last``."""
    program = [
        (_LDH_ABS, 0, 0, 12),
        (_JEQ, 0, 4, ETHERTYPE),
        (_LDB_ABS, 0, 0, FIRST_INDEX_OFFSET),
        (_JGE, 0, 2, first),
        (_JGT, 1, 0, last),
        (_RET, 0, 0, 0x40000),
        (_RET, 0, 0, 0),
    ]
    return b"".join(_FILTER.pack(*instruction) for instruction in program)


def attach_filter(sock: socket.socket, program: bytes) -> None:
    """Attach a classic BPF ``program`` (packed sock_filter entries) to ``sock``."""
    buffer = ctypes.create_string_buffer(program)
    fprog = struct.pack("HL", len(program) // _FILTER.size, ctypes.addressof(buffer))
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)


class SocketWire:
    """A raw socket on ``interface`` that receives only frames with indices ``first..last``."""

    def __init__(self, interface: str, first: int, last: int) -> None:
        self._sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETHERTYPE))
        try:
            attach_filter(self._sock, index_filter(first, last))
            self._sock.bind((interface, ETHERTYPE))
            self._sock.setblocking(False)
            while True:  # frames that came in before the filter was attached
                try:
                    self._sock.recv(2048)
                except BlockingIOError:
                    break
            self._sock.setblocking(True)
        except BaseException:
            self._sock.close()
            raise
        self._buffer = bytearray(2048)

    def send(self, frame: bytes) -> None:
        self._sock.send(frame)

    def receive(self, timeout_s: float) -> bytes | None:
        self._sock.settimeout(max(timeout_s, 1e-6))
        try:
            size = self._sock.recv_into(self._buffer)
        except (TimeoutError, BlockingIOError):
            return None
        return bytes(self._buffer[:size])

    def close(self) -> None:
        self._sock.close()


def index_ranges(channels: int) -> list[range]:
    """``channels`` disjoint ranges of our indices, as even as they go."""
    total = LAST_INDEX - FIRST_INDEX + 1
    if not 1 <= channels <= total // 2:
        raise ValueError(f"{channels} channels cannot each have 2 of our {total} datagram indices")
    size = total // channels
    return [range(FIRST_INDEX + k * size, FIRST_INDEX + (k + 1) * size) for k in range(channels)]
