"""One slave's CoE mailbox, driven over Prime's own frames (``link.py``): SDO upload and download, each reply
matched to its request.

Why not SOEM's (ethercatcoe.c): ``ecx_SDOread`` takes the first CoE message in the read mailbox as its answer,
checking the object index only, so a late reply to an earlier write of the same object reads as a value of 0
bytes (its PDO mapping read-back then counts that entry as 0 bits); and its lost-reply path writes SM1's status
word back from a copy that may come from a late frame (``link.py``). Here:

- one transfer at a time per slave (a lock): no two threads in one slave's mailbox;
- whatever waits in the read mailbox when a request goes out (a reply that came after its request was given up
  on) is taken out in the same frame, before the request, and dropped;
- a reply is taken only if it answers this request: the same object and sub-index and the kind of reply the
  request asks for (upload or download; a segment with the expected toggle). Anything else found meanwhile is
  dropped and counted, and a reply whose counter repeats the last one's is a repeat of an old reply;
- each request carries its counter (ETG.1000.4), the same one when its frame is sent again, so a slave that got
  it once serves it once. The first request after another master used this mailbox (SOEM reads the PDO mapping
  back through it) carries counter 0, which no slave takes for a repeat (sent twice, it may be served twice: every
  object Prime writes takes the same value twice), and the counters skip 1, the one SOEM's first request after a
  ring scan carries;
- a reply read out of the slave but lost on its way back (the frame did not come back) is asked for again;
  nothing here writes a SyncManager register;
- emergencies found in the mailbox go to ``on_emergency``.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

from humanoid_prime.drivers.ethercat.errors import SdoError
from humanoid_prime.drivers.ethercat.link import Channel, fprd, fpwr
from humanoid_prime.drivers.ethercat.wire import (
    COE_EMERGENCY,
    COE_SDO_REQUEST,
    COE_SDO_RESPONSE,
    MAILBOX_ERRORS,
    MAILBOX_HEADER,
    MAILBOX_TYPE_COE,
    MAILBOX_TYPE_ERROR,
    SDO_ABORT,
    SDO_HEADER,
    abort_text,
)

FRAME_TIMEOUT_S = 0.05  # a mailbox frame not back by then is lost (a stalled host holds frames for tens of ms)
POLL_S = 0.0002  # between looks at the read mailbox (SOEM's EC_LOCALDELAY)
REQUEST_ATTEMPTS = 4  # a request sent afresh after its reply was lost on the way back
COUNTERS = (2, 3, 4, 5, 6, 7)  # skipping 1: SOEM's first request after a ring scan carries it
_HEADER = MAILBOX_HEADER
_SDO = SDO_HEADER


@dataclass(frozen=True)
class MailboxLayout:
    """Where the slave's mailboxes are, as SM0 (master to slave) and SM1 (slave to master) say."""

    write_start: int
    write_size: int
    read_start: int
    read_size: int


@dataclass(frozen=True)
class DroppedReply:
    at: float
    what: str  # what it answered, in words
    waited_s: float  # from the request it came during (or was found before) to when it was read


class CoeMailbox:
    """SDO access to the slave at ring ``position`` (station address ``station``) through ``channel``."""

    def __init__(self, channel: Channel, position: int, station: int, layout: MailboxLayout, *,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], object] = time.sleep,
                 on_emergency: Callable[[int, int], None] | None = None,
                 frame_timeout_s: float = FRAME_TIMEOUT_S) -> None:
        self.channel = channel
        self.position = position
        self.station = station
        self.layout = layout
        self.clock = clock
        self.sleep = sleep
        self.on_emergency = on_emergency
        self.frame_timeout_s = frame_timeout_s
        self.dropped: list[DroppedReply] = []  # replies that answered no request in flight (late ones)
        self.requests_again = 0  # requests sent afresh because their reply was lost on the way back
        self._counter = 0  # 0: the next request carries 0 (another master may have used the mailbox)
        self._last_reply: tuple[int, bytes] | None = None  # (counter, message) of the last reply read
        self._lock = threading.Lock()

    def shared(self) -> None:
        """Another master used this mailbox since our last request: the next request carries counter 0."""
        with self._lock:
            self._counter = 0

    # --------------------------------------------------------------------------------------------- SDO
    def download(self, index: int, sub: int, data: bytes, timeout_s: float) -> None:
        """Write ``data`` to object ``index``:``sub`` (expedited up to 4 bytes, else in one normal message)."""
        data = bytes(data)
        if 1 <= len(data) <= 4:
            payload = _SDO.pack(COE_SDO_REQUEST << 12, 0x23 | ((4 - len(data)) << 2), index, sub) + data.ljust(4, b"\0")
        elif len(data) <= self.layout.write_size - 16:
            payload = _SDO.pack(COE_SDO_REQUEST << 12, 0x21, index, sub) + struct.pack("<I", len(data)) + data
        else:
            raise SdoError(self.position, index, sub, f"{len(data)} bytes do not fit one mailbox message "
                                                     f"({self.layout.write_size - 16} at most; no segmented download)")
        with self._lock:
            self._transfer(index, sub, payload, lambda coe: _is_response(coe, index, sub, 0x60, 0xFF), timeout_s)

    def upload(self, index: int, sub: int, timeout_s: float) -> bytes:
        """The value of object ``index``:``sub`` (expedited, normal or segmented)."""
        payload = _SDO.pack(COE_SDO_REQUEST << 12, 0x40, index, sub) + bytes(4)
        with self._lock:
            deadline = self.clock() + timeout_s
            coe = self._transfer(index, sub, payload, lambda coe: _is_response(coe, index, sub, 0x40, 0xE0), timeout_s)
            command = coe[2]
            if command & 0x02:  # expedited
                size = 4 - ((command >> 2) & 0x03) if command & 0x01 else 4
                return bytes(coe[6:6 + size])
            if len(coe) < 10:
                raise SdoError(self.position, index, sub, "upload reply too short")
            total = struct.unpack_from("<I", coe, 6)[0]
            data = bytearray(coe[10:10 + total])
            toggle = 0x00
            while len(data) < total:
                request = struct.pack("<HB", COE_SDO_REQUEST << 12, 0x60 | toggle) + bytes(7)
                segment = self._transfer(index, sub, request, partial(_is_segment, toggle=toggle),
                                         max(deadline - self.clock(), 0.0))
                unused = (segment[2] >> 1) & 0x07 if len(segment) == 10 else 0
                data += segment[3:len(segment) - unused]
                if segment[2] & 0x01:
                    break
                toggle ^= 0x10
            return bytes(data[:total])

    # ------------------------------------------------------------------------------------------ transfer
    def _transfer(self, index: int, sub: int, payload: bytes, answers: Callable[[bytes], bool],
                  timeout_s: float) -> bytes:
        """Send ``payload`` and return the CoE part of the reply that ``answers`` it; SdoError for an abort, a
        mailbox error, or no reply in ``timeout_s``."""
        deadline = self.clock() + timeout_s
        for _attempt in range(REQUEST_ATTEMPTS):
            counter = self._take_counter()
            message = _HEADER.pack(len(payload), 0, 0, MAILBOX_TYPE_COE | (counter << 4)) + payload
            message = message.ljust(self.layout.write_size, b"\0")
            sent = self.clock()
            if not self._send(message, deadline, sent):
                break
            reply = self._await_reply(index, sub, answers, deadline, sent)
            if reply is not None:
                return reply
            if self.clock() >= deadline:
                break
            self.requests_again += 1  # the reply was read out but its frame did not come back: ask again
        raise SdoError(self.position, index, sub, f"no reply within {timeout_s * 1e3:g} ms (mailbox timeout)")

    def _send(self, message: bytes, deadline: float, sent: float) -> bool:
        """Take out whatever waits in the read mailbox, then put the request in the write mailbox; False when it
        could not be delivered before ``deadline``."""
        layout, station = self.layout, self.station
        flush = fprd(station, layout.read_start, layout.read_size)
        request = fpwr(station, layout.write_start, message)
        replies = self.channel.exchange([flush, request], timeout_s=self._frame_time(deadline), repeat=False)
        if replies is not None:
            if replies[0].wkc == 1 and not self._emergency(replies[0].data):
                self._drop(replies[0].data, sent, "found before the request")
            if replies[1].wkc == 1:
                return True
        while self.clock() < deadline:  # lost, or refused while the write mailbox still held a request: again
            self.sleep(POLL_S)
            again = self.channel.exchange([request], timeout_s=self._frame_time(deadline))
            if again is not None and again[0].wkc == 1:
                return True
        return False

    def _await_reply(self, index: int, sub: int, answers: Callable[[bytes], bool], deadline: float,
                     sent: float) -> bytes | None:
        """Poll the read mailbox for the reply that ``answers`` the request; None when a reply was read out but
        its frame did not come back (the request must go again), or at ``deadline``."""
        layout = self.layout
        read = fprd(self.station, layout.read_start, layout.read_size)
        while self.clock() < deadline:
            replies = self.channel.exchange([read], timeout_s=self._frame_time(deadline), repeat=False)
            if replies is None:
                return None
            if replies[0].wkc != 1:
                self.sleep(POLL_S)
                continue
            message = replies[0].data
            length, _address, _channel, kind = _HEADER.unpack_from(message)
            counter, coe = (kind >> 4) & 0x07, message[_HEADER.size:_HEADER.size + length]
            if self._last_reply == (counter, message) and counter:
                continue  # a repeat of the last reply (the slave offered it again)
            self._last_reply = (counter, message)
            if kind & 0x0F == MAILBOX_TYPE_ERROR:
                detail = struct.unpack_from("<H", coe, 2)[0] if len(coe) >= 4 else 0
                raise SdoError(self.position, index, sub,
                               f"mailbox error {detail} ({MAILBOX_ERRORS.get(detail, 'unknown')})")
            if self._emergency(message):
                continue
            if kind & 0x0F == MAILBOX_TYPE_COE and _is_abort(coe, index, sub):
                code = struct.unpack_from("<I", coe, 6)[0]
                raise SdoError(self.position, index, sub, f"aborted with 0x{code:08X} ({abort_text(code)})", code)
            if kind & 0x0F == MAILBOX_TYPE_COE and answers(coe):
                return bytes(coe)
            self._drop(message, sent, "while another request waited")
        return None

    def _emergency(self, message: bytes) -> bool:
        """Hand an emergency message on; False for any other message."""
        length, _address, _channel, kind = _HEADER.unpack_from(message)
        coe = message[_HEADER.size:_HEADER.size + length]
        if kind & 0x0F != MAILBOX_TYPE_COE or len(coe) < 4 or coe[1] >> 4 != COE_EMERGENCY:
            return False
        if self.on_emergency is not None:
            self.on_emergency(self.position, struct.unpack_from("<H", coe, 2)[0])
        return True

    def _drop(self, message: bytes, sent: float, when: str) -> None:
        now = self.clock()
        self.dropped.append(DroppedReply(now, f"{describe_message(message)}, {when}", now - sent))
        del self.dropped[:-64]

    def _take_counter(self) -> int:
        counter = self._counter
        self._counter = COUNTERS[(COUNTERS.index(counter) + 1) % len(COUNTERS)] if counter else COUNTERS[0]
        return counter

    def _frame_time(self, deadline: float) -> float:
        return max(min(self.frame_timeout_s, deadline - self.clock()), 1e-4)


def _is_response(coe: bytes, index: int, sub: int, command: int, mask: int) -> bool:
    if len(coe) < 6 or coe[1] >> 4 != COE_SDO_RESPONSE:
        return False
    command_byte, got_index, got_sub = struct.unpack_from("<BHB", coe, 2)
    return command_byte & mask == command and (got_index, got_sub) == (index, sub)


def _is_segment(coe: bytes, toggle: int) -> bool:
    return len(coe) >= 3 and coe[1] >> 4 == COE_SDO_RESPONSE and coe[2] >> 5 == 0 and coe[2] & 0x10 == toggle


def _is_abort(coe: bytes, index: int, sub: int) -> bool:
    if len(coe) < 10 or coe[1] >> 4 not in (COE_SDO_REQUEST, COE_SDO_RESPONSE) or coe[2] != SDO_ABORT:
        return False
    return struct.unpack_from("<HB", coe, 3) == (index, sub)


def describe_message(message: bytes) -> str:
    """A mailbox message in words (for the record of replies dropped)."""
    if len(message) < _HEADER.size + 6:
        return "a short mailbox message"
    coe = message[_HEADER.size:]
    command, index, sub = struct.unpack_from("<BHB", coe, 2)
    if command >> 5 not in (2, 3, 4):
        return "an SDO segment"
    kind = {2: "an upload reply", 3: "a download reply", 4: "an abort"}[command >> 5]
    return f"{kind} for 0x{index:04X}:{sub:02X}"
