"""One slave's CoE mailbox, driven over Prime's own frames (``link.py``): SDO upload and download, each reply
matched to its request on what identifies it (``coe.py``).

Why not SOEM's (ethercatcoe.c): ``ecx_SDOread`` takes the first CoE message in the read mailbox as its answer,
checking the object index only, so a late reply to an earlier write of the same object reads as a value of 0 bytes
(its PDO mapping read-back then counts that entry as 0 bits); and its lost-reply path writes SM1's status word back
from a copy that may come from a late frame (``link.py``). Here:

- one transfer at a time per slave (a lock): no two threads in one slave's mailbox;
- whatever waits in the read mailbox when a request goes out is taken out in the same frame, before the request;
- a reply is taken only if it answers this request (``coe.Expected``); anything else found meanwhile is dropped and
  counted by why (``drops``): late (it answers a request sent earlier), for another object, unrecognised (the byte
  is named), malformed. Emergencies go to ``on_emergency`` and are counted apart;
- each request carries a counter (ETG.1000.4), the same one when its frame is sent again, so a slave that got it
  once serves it once: 0 for the next request after ``reset_counter`` (0 is never a repeat, so another master's
  requests before and after it cannot be taken for one), then 1..7, 1 after 7. The slave's counter in its replies
  is its own sequence and is not compared with ours;
- a reply read out of the slave but lost on its way back (the frame did not come back) is asked for again with a
  fresh request; nothing here writes a SyncManager register.
"""

from __future__ import annotations

import collections
import math
import struct
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

from humanoid_prime.drivers.ethercat.coe import (
    ABORT,
    DROP_REASONS,
    EMERGENCY,
    LATE,
    MAILBOX_ERROR,
    MALFORMED,
    OTHER_OBJECT,
    UNRECOGNISED,
    Expected,
    Message,
    mailbox_error_text,
    read_message,
    segment_data,
    upload_value,
    why_dropped,
)
from humanoid_prime.drivers.ethercat.errors import SdoError, SdoTimeout
from humanoid_prime.drivers.ethercat.link import Channel, Reply, Request, fprd, fpwr
from humanoid_prime.drivers.ethercat.wire import (
    COE_SDO_REQUEST,
    COE_SERVICE_SHIFT,
    MAILBOX_HEADER_SIZE,
    MAILBOX_TYPE_COE,
    SCS_DOWNLOAD,
    SCS_UPLOAD,
    SCS_UPLOAD_SEGMENT,
    SDO_DOWNLOAD_NORMAL,
    SDO_HEADER,
    SDO_MIN_LENGTH,
    SDO_TOGGLE,
    SDO_UPLOAD_REQUEST,
    SDO_UPLOAD_SEGMENT_REQUEST,
    abort_text,
    mailbox_message,
    sdo_download_expedited,
)

FRAME_TIMEOUT_S = 0.05  # a mailbox frame not back by then is lost (a stalled host holds frames for tens of ms)
POLL_S = 0.0002  # between looks at the read mailbox (SOEM's EC_LOCALDELAY)
REQUEST_ATTEMPTS = 4  # a request sent afresh after its reply was lost on the way back
REMEMBERED = 16  # requests kept to tell a late reply from one for another object
DROPS_KEPT = 64
_LABELS = {LATE: "late", OTHER_OBJECT: "for another object", UNRECOGNISED: "unrecognised", MALFORMED: "malformed"}


class SdoMailbox(Protocol):
    """One slave's SDO transfers, whoever works its mailbox (``CoeMailbox``, or SOEM's: ``SoemMailbox``)."""

    def download(self, index: int, sub: int, data: bytes, timeout_s: float) -> None: ...

    def upload(self, index: int, sub: int, timeout_s: float) -> bytes: ...

    def reset_counter(self) -> None: ...


@dataclass(frozen=True)
class MailboxLayout:
    """Where the slave's mailboxes are, as SM0 (master to slave) and SM1 (slave to master) say."""

    write_start: int
    write_size: int
    read_start: int
    read_size: int


@dataclass(frozen=True)
class DroppedReply:
    """A message read out of a slave's mailbox that answered no request in flight."""

    at: float
    position: int
    reason: str  # coe.DROP_REASONS
    what: str  # the message, in words
    late_s: float | None = None  # late: how long after the request it answers


@dataclass
class _Wait:
    """What one transfer's wait saw: the request taken by the write mailbox, looks at the read mailbox, and the
    longest time between two frames to the slave (``clock`` time)."""

    last: float
    delivered: bool = False
    looks: int = 0
    longest_gap_s: float = 0.0


class DropLog:
    """The messages the mailboxes of a ring dropped: a count by reason, and the latest of them."""

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter({reason: 0 for reason in DROP_REASONS})
        self.records: collections.deque[DroppedReply] = collections.deque(maxlen=DROPS_KEPT)
        self.emergencies = 0
        # Requests whose reply was given up on (asked again, or timed out): a late drop mostly answers one of them
        # (or a request of SOEM's at start-up, or a request a slave served twice).
        self.given_up = 0
        self._lock = threading.Lock()

    def add(self, record: DroppedReply) -> None:
        with self._lock:
            self.counts[record.reason] += 1
            self.records.append(record)

    def give_up(self) -> None:
        """A request's reply is no longer awaited."""
        with self._lock:
            self.given_up += 1

    def emergency(self) -> None:
        """An emergency message was read out (the mailboxes of a ring share this log, each in its own thread)."""
        with self._lock:
            self.emergencies += 1

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return {reason: self.counts[reason] for reason in DROP_REASONS}

    def describe(self, since: Mapping[str, int] | None = None, after: float = -math.inf) -> str:
        """The drops since the counts were ``since`` (and since ``after``, for the latest of each), in words."""
        now = self.snapshot()
        counts = {reason: now[reason] - (since or {}).get(reason, 0) for reason in DROP_REASONS}
        return describe_drops(counts, [r for r in list(self.records) if r.at >= after])


class CoeMailbox:
    """SDO access to the slave at ring ``position`` (station address ``station``) through ``channel``."""

    def __init__(self, channel: Channel, position: int, station: int, layout: MailboxLayout, *,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], object] = time.sleep,
                 on_emergency: Callable[[int, int], None] | None = None,
                 frame_timeout_s: float = FRAME_TIMEOUT_S, log: DropLog | None = None) -> None:
        self.channel = channel
        self.position = position
        self.station = station
        self.layout = layout
        self.clock = clock
        self.sleep = sleep
        self.on_emergency = on_emergency
        self.frame_timeout_s = frame_timeout_s
        self.log = log if log is not None else DropLog()
        self.requests_again = 0  # requests sent afresh because their reply was lost on the way back
        self._counter = 0  # the next request carries 0, then 1..7
        self._sent: collections.deque[Expected] = collections.deque(maxlen=REMEMBERED)  # in flight last
        self._wait = _Wait(0.0)
        self._lock = threading.Lock()

    def reset_counter(self) -> None:
        """The next request carries counter 0: call it after another master used this mailbox, and before the last
        request ahead of its use (that master's counters, 1 to 7, can repeat neither)."""
        with self._lock:
            self._counter = 0

    # --------------------------------------------------------------------------------------------- SDO
    def download(self, index: int, sub: int, data: bytes, timeout_s: float) -> None:
        """Write ``data`` to object ``index``:``sub`` (expedited up to 4 bytes, else in one normal message)."""
        data = bytes(data)
        if 1 <= len(data) <= 4:
            payload = _sdo(sdo_download_expedited(len(data)), index, sub, data.ljust(4, b"\0"))
        elif len(data) <= self.layout.write_size - MAILBOX_HEADER_SIZE - SDO_MIN_LENGTH:
            payload = _sdo(SDO_DOWNLOAD_NORMAL, index, sub, struct.pack("<I", len(data)) + data)
        else:
            room = self.layout.write_size - MAILBOX_HEADER_SIZE - SDO_MIN_LENGTH
            raise SdoError(self.position, index, sub, f"{len(data)} bytes do not fit one mailbox message "
                                                     f"({room} at most; no segmented download)")
        with self._lock:
            self._transfer(payload, Expected(SCS_DOWNLOAD, index, sub), timeout_s)

    def upload(self, index: int, sub: int, timeout_s: float) -> bytes:
        """The value of object ``index``:``sub``, whichever legal encoding the slave answers in."""
        with self._lock:
            deadline = self.clock() + timeout_s
            reply = self._transfer(_sdo(SDO_UPLOAD_REQUEST, index, sub), Expected(SCS_UPLOAD, index, sub), timeout_s)
            try:
                first, total = upload_value(reply)
            except ValueError as exc:
                raise SdoError(self.position, index, sub, f"the upload reply is malformed: {exc}") from None
            data = bytearray(first)
            toggle = 0
            while len(data) < total:
                request = struct.pack("<HB", COE_SDO_REQUEST << COE_SERVICE_SHIFT,
                                      SDO_UPLOAD_SEGMENT_REQUEST | toggle) + bytes(7)
                segment = self._transfer(request, Expected(SCS_UPLOAD_SEGMENT, index, sub, toggle),
                                         max(deadline - self.clock(), 0.0))
                chunk, last = segment_data(segment)
                data += chunk
                if last:
                    break
                toggle ^= SDO_TOGGLE
            return bytes(data[:total])

    # ------------------------------------------------------------------------------------------ transfer
    def _transfer(self, payload: bytes, expected: Expected, timeout_s: float) -> Message:
        """Send ``payload`` and return the reply that answers it; SdoError for an abort, a mailbox error, or no reply
        in ``timeout_s``."""
        index, sub = expected.index, expected.sub
        deadline = self.clock() + timeout_s
        self._wait = _Wait(self.clock())
        for attempt in range(REQUEST_ATTEMPTS):
            message = mailbox_message(payload, MAILBOX_TYPE_COE, self._take_counter())
            message = message.ljust(self.layout.write_size, b"\0")
            sent = Expected(expected.specifier, index, sub, expected.toggle, self.clock())
            if not self._send(message, deadline):
                self.log.give_up()  # (its frame may have reached the slave)
                break
            self._wait.delivered = True
            self._sent.append(sent)
            reply = self._await_reply(sent, deadline)
            if reply is not None:
                return reply
            self.log.give_up()
            if self.clock() >= deadline or attempt == REQUEST_ATTEMPTS - 1:
                break
            self.requests_again += 1  # the reply was read out but its frame did not come back: ask again
        wait = self._wait
        raise SdoTimeout(self.position, index, sub, timeout_s, delivered=wait.delivered, looks=wait.looks,
                         longest_gap_s=max(wait.longest_gap_s, self.clock() - wait.last))

    def _send(self, message: bytes, deadline: float) -> bool:
        """Take out whatever waits in the read mailbox, then put the request in the write mailbox; False when it
        could not be delivered before ``deadline``."""
        layout, station = self.layout, self.station
        flush = fprd(station, layout.read_start, layout.read_size)
        request = fpwr(station, layout.write_start, message)
        replies = self._exchange([flush, request], deadline, repeat=False)
        if replies is not None:
            if replies[0].wkc == 1:
                self._unasked(read_message(replies[0].data))
            if replies[1].wkc == 1:
                return True
        while self.clock() < deadline:  # lost, or refused while the write mailbox still held a request: again
            self.sleep(POLL_S)
            again = self._exchange([request], deadline)
            if again is not None and again[0].wkc == 1:
                return True
        return False

    def _await_reply(self, expected: Expected, deadline: float) -> Message | None:
        """Poll the read mailbox for the reply that answers ``expected``; None when a reply was read out but its
        frame did not come back (the request must go again), or at ``deadline``."""
        layout = self.layout
        read = fprd(self.station, layout.read_start, layout.read_size)
        while self.clock() < deadline:
            replies = self._exchange([read], deadline, repeat=False)
            if replies is None:
                return None
            self._wait.looks += 1
            if replies[0].wkc != 1:
                self.sleep(POLL_S)
                continue
            reply = read_message(replies[0].data)
            if reply.kind == MAILBOX_ERROR:
                raise SdoError(self.position, expected.index, expected.sub, mailbox_error_text(reply.detail))
            if expected.answered_by(reply):
                if reply.kind == ABORT:
                    raise SdoError(self.position, expected.index, expected.sub,
                                   f"aborted with 0x{reply.detail:08X} ({abort_text(reply.detail)})", reply.detail)
                return reply
            self._unasked(reply, in_flight=expected)
        return None

    def _unasked(self, reply: Message, in_flight: Expected | None = None) -> None:
        """A message that answers no request in flight: an emergency is handed on; anything else dropped and
        counted by why."""
        if reply.kind == EMERGENCY:
            self.log.emergency()
            if self.on_emergency is not None:
                self.on_emergency(self.position, reply.detail)
            return
        earlier = [sent for sent in self._sent if sent is not in_flight]
        reason, answered = why_dropped(reply, earlier)
        now = self.clock()
        late_s = now - answered.sent_at if answered is not None else None
        what = reply.describe() if reason != LATE else f"{reply.describe()}, answering {answered}"
        self.log.add(DroppedReply(now, self.position, reason, what, late_s))

    def _take_counter(self) -> int:
        counter = self._counter
        self._counter = counter % 7 + 1
        return counter

    def _exchange(self, requests: Sequence[Request], deadline: float, repeat: bool = True) -> list[Reply] | None:
        """One frame to the slave, the time since the last one counted (how long this process went without a look)."""
        wait = self._wait
        began = self.clock()
        wait.longest_gap_s = max(wait.longest_gap_s, began - wait.last)
        try:
            return self.channel.exchange(requests, timeout_s=self._frame_time(deadline), repeat=repeat)
        finally:
            wait.last = self.clock()

    def _frame_time(self, deadline: float) -> float:
        return max(min(self.frame_timeout_s, deadline - self.clock()), 1e-4)


def _sdo(command: int, index: int, sub: int, data: bytes = bytes(4)) -> bytes:
    return SDO_HEADER.pack(COE_SDO_REQUEST << COE_SERVICE_SHIFT, command, index, sub) + data


def describe_drops(drops: Mapping[str, int], dropped: Sequence[DroppedReply]) -> str:
    """The mailbox messages dropped, by why, in words ('' when none): the latest of each kind named."""
    parts = []
    for reason in DROP_REASONS:
        count = drops.get(reason, 0)
        if not count:
            continue
        latest = next((d for d in reversed(dropped) if d.reason == reason), None)
        if reason == LATE:
            text = f"{count} late (each answered an earlier request"
            if latest is not None and latest.late_s is not None:
                text += f"; the latest, ring {latest.position}, {latest.late_s * 1e3:.0f} ms after it: {latest.what}"
            parts.append(text + ")")
        else:
            parts.append(f"{count} {_LABELS[reason]}"
                         + (f" (the latest, ring {latest.position}: {latest.what})" if latest is not None else ""))
    return "; ".join(parts)
