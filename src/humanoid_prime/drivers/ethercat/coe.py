"""CoE replies as a master reads them: what a mailbox message is, whether it answers a request, and why one that
does not is dropped.

A reply is matched on what identifies it and nothing else: the mailbox type (CoE), the CoE service (SDO response;
an abort under either SDO service), the command specifier (the command byte's top three bits), the object and
sub-index, and for a segment its toggle bit. Reserved bits are ignored, and so is the mailbox counter of the reply,
which is the slave's own sequence (ETG.1000.4), never an echo of the request's. Every legal encoding of a value is
taken: expedited with or without a size indication (without one, all four bytes), or normal, in one message or in
segments. SOEM's ecx_SDOread checks the type, the service and the index only; IgH's fsm_coe.c the specifier, the
index and the sub-index, and looks again on a mismatch; EtherCrab reads the top three bits and checks the index and
sub-index, not the counter (its #236) -- this layer checks what IgH does, and the toggle.

A message that answers no request in flight is dropped and named for what it was: ``late`` (it answers a request
sent earlier: only then), ``other object`` (a well-formed reply for an object nobody asked for), ``unrecognised``
(a mailbox type, CoE service or command byte this master does not take; the byte is named) or ``malformed`` (too
short for what it says it is).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

from humanoid_prime.drivers.ethercat.wire import (
    COE_EMERGENCY,
    COE_SDO_REQUEST,
    COE_SDO_RESPONSE,
    CS_ABORT,
    MAILBOX_ERRORS,
    MAILBOX_HEADER,
    MAILBOX_HEADER_SIZE,
    MAILBOX_TYPE_COE,
    MAILBOX_TYPE_ERROR,
    MAILBOX_TYPE_MASK,
    MAILBOX_TYPE_NAMES,
    SCS_DOWNLOAD,
    SCS_DOWNLOAD_SEGMENT,
    SCS_NAMES,
    SCS_UPLOAD,
    SCS_UPLOAD_SEGMENT,
    SDO_EXPEDITED,
    SDO_LAST_SEGMENT,
    SDO_MIN_LENGTH,
    SDO_SEGMENT_DATA,
    SDO_SEGMENT_UNUSED_SHIFT,
    SDO_TOGGLE,
    command_specifier,
    expedited_size,
)

LATE, OTHER_OBJECT, UNRECOGNISED, MALFORMED = "late", "other object", "unrecognised", "malformed"
DROP_REASONS = (LATE, OTHER_OBJECT, UNRECOGNISED, MALFORMED)
SDO, ABORT, EMERGENCY, MAILBOX_ERROR = "sdo", "abort", "emergency", "mailbox error"
_INITIATE = (SCS_DOWNLOAD, SCS_UPLOAD)  # replies that name their object
_SEGMENTS = (SCS_UPLOAD_SEGMENT, SCS_DOWNLOAD_SEGMENT)  # replies that carry a toggle instead
_OBJECT = struct.Struct("<HB")  # index, sub-index after the command byte


@dataclass(frozen=True)
class Expected:
    """What answers a request: a reply with the server specifier ``specifier`` for ``index``:``sub`` (a segment:
    with ``toggle``); ``sent_at`` is when the request went out."""

    specifier: int
    index: int
    sub: int
    toggle: int = 0
    sent_at: float = 0.0

    def answered_by(self, reply: Message) -> bool:
        if reply.kind == ABORT:
            return (reply.index, reply.sub) == (self.index, self.sub)
        if reply.kind != SDO or reply.specifier != self.specifier:
            return False
        if self.specifier in _SEGMENTS:
            return reply.toggle == self.toggle
        return (reply.index, reply.sub) == (self.index, self.sub)

    def __str__(self) -> str:
        what = SCS_NAMES[self.specifier]
        return f"{what} for 0x{self.index:04X}:{self.sub:02X}"


@dataclass(frozen=True)
class Message:
    """One message read out of a slave's read mailbox. ``kind``: SDO (a reply with ``specifier``), ABORT (``detail``
    the abort code), EMERGENCY (``detail`` the error code), MAILBOX_ERROR (``detail`` the error), or a drop reason
    (UNRECOGNISED, MALFORMED) with ``text`` naming what did not fit. ``coe`` is the CoE payload."""

    kind: str
    specifier: int = -1
    index: int = -1
    sub: int = -1
    toggle: int = 0
    command: int = 0
    detail: int = 0
    coe: bytes = b""
    text: str = ""

    def describe(self) -> str:
        if self.kind in (UNRECOGNISED, MALFORMED):
            return self.text
        if self.kind == ABORT:
            return f"an abort 0x{self.detail:08X} for 0x{self.index:04X}:{self.sub:02X}"
        if self.kind == SDO and self.specifier in _SEGMENTS:
            return f"{SCS_NAMES[self.specifier]} with toggle {int(bool(self.toggle))}"
        if self.kind == SDO:
            what = f"{SCS_NAMES[self.specifier]} for 0x{self.index:04X}:{self.sub:02X}"
            return f"{what} (command byte 0x{self.command:02X})"
        return self.kind


def read_message(message: bytes) -> Message:
    """What the mailbox message ``message`` (header included) is."""
    if len(message) < MAILBOX_HEADER_SIZE:
        return Message(MALFORMED, text=f"a message of {len(message)} bytes, shorter than the mailbox header")
    length, _address, _channel, type_byte = MAILBOX_HEADER.unpack_from(message)
    if MAILBOX_HEADER_SIZE + length > len(message):
        return Message(MALFORMED, text=f"a mailbox header announcing {length} bytes in a mailbox of {len(message)}")
    payload = bytes(message[MAILBOX_HEADER_SIZE:MAILBOX_HEADER_SIZE + length])
    mailbox_type = type_byte & MAILBOX_TYPE_MASK
    if mailbox_type == MAILBOX_TYPE_ERROR:
        detail = struct.unpack_from("<H", payload, 2)[0] if len(payload) >= 4 else 0
        return Message(MAILBOX_ERROR, detail=detail, coe=payload)
    if mailbox_type != MAILBOX_TYPE_COE:
        name = MAILBOX_TYPE_NAMES.get(mailbox_type, "unknown")
        return Message(UNRECOGNISED, text=f"mailbox type 0x{mailbox_type:X} ({name}), type byte 0x{type_byte:02X}")
    if len(payload) < 2:
        return Message(MALFORMED, text=f"a CoE message of {len(payload)} bytes")
    service = payload[1] >> 4
    if service == COE_EMERGENCY:
        if len(payload) < 4:
            return Message(MALFORMED, text=f"an emergency of {len(payload)} bytes")
        return Message(EMERGENCY, detail=struct.unpack_from("<H", payload, 2)[0], coe=payload)
    if service not in (COE_SDO_REQUEST, COE_SDO_RESPONSE) or len(payload) < 3:
        return Message(UNRECOGNISED, text=f"CoE service {service} (header byte 0x{payload[1]:02X})")
    command = payload[2]
    specifier = command_specifier(command)
    if specifier == CS_ABORT:  # under the request service as ETG.1000.6 has it, or the response's (SOES #115)
        if len(payload) < SDO_MIN_LENGTH:
            return Message(MALFORMED, text=f"an abort of {len(payload)} bytes (command byte 0x{command:02X})")
        index, sub = _OBJECT.unpack_from(payload, 3)
        return Message(ABORT, CS_ABORT, index, sub, command=command, detail=struct.unpack_from("<I", payload, 6)[0],
                       coe=payload)
    if service != COE_SDO_RESPONSE or specifier not in (*_INITIATE, *_SEGMENTS):
        return Message(UNRECOGNISED, text=f"command byte 0x{command:02X} under CoE service {service}")
    if specifier in _SEGMENTS:
        return Message(SDO, specifier, toggle=command & SDO_TOGGLE, command=command, coe=payload)
    if len(payload) < 6:
        return Message(MALFORMED, text=f"{SCS_NAMES[specifier]} of {len(payload)} bytes (command byte 0x{command:02X})")
    index, sub = _OBJECT.unpack_from(payload, 3)
    return Message(SDO, specifier, index, sub, command=command, coe=payload)


def upload_value(reply: Message) -> tuple[bytes, int]:
    """(the data an upload reply carries, the value's whole size): expedited (its size indicated, or all four
    bytes), or normal (the size u32, then as much data as the message holds); ValueError when the message is too
    short for what it says."""
    coe, command = reply.coe, reply.command
    if command & SDO_EXPEDITED:
        size = expedited_size(command)
        if len(coe) < 6 + size:
            raise ValueError(f"an expedited upload of {size} bytes in a message of {len(coe)}")
        return coe[6:6 + size], size
    if len(coe) < SDO_MIN_LENGTH:
        raise ValueError(f"a normal upload of {len(coe)} bytes, too short for its size")
    total: int = struct.unpack_from("<I", coe, 6)[0]
    return coe[SDO_MIN_LENGTH:SDO_MIN_LENGTH + total], total


def segment_data(reply: Message) -> tuple[bytes, bool]:
    """(the data of an upload segment, whether it is the last): a segment of the minimum length says in bits 1-3
    how many of its seven data bytes are unused."""
    coe, command = reply.coe, reply.command
    if len(coe) == SDO_MIN_LENGTH:
        unused = (command >> SDO_SEGMENT_UNUSED_SHIFT) & 0x07
        data = coe[3:3 + SDO_SEGMENT_DATA - unused]
    else:
        data = coe[3:]
    return data, bool(command & SDO_LAST_SEGMENT)


def mailbox_error_text(detail: int) -> str:
    return f"mailbox error {detail} ({MAILBOX_ERRORS.get(detail, 'unknown')})"


def why_dropped(reply: Message, earlier: Sequence[Expected]) -> tuple[str, Expected | None]:
    """Why ``reply``, which answers no request in flight, is dropped: LATE with the earlier request it answers (the
    latest such), OTHER_OBJECT for a well-formed reply nobody asked for, or its own reason (UNRECOGNISED,
    MALFORMED)."""
    if reply.kind in (UNRECOGNISED, MALFORMED):
        return reply.kind, None
    for request in reversed(earlier):
        if request.answered_by(reply):
            return LATE, request
    return OTHER_OBJECT, None
