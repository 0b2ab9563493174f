"""The slave side of the EtherCAT mailbox and of CoE SDO transfers (ETG.1000.4 / ETG.1000.6; the encodings are
``drivers/ethercat/wire.py``'s).

Mailbox message: header of 6 bytes -- length u16 (bytes after the header), address u16, channel and priority u8,
type (bits 0-3; 3 = CoE) and counter (bits 4-6, 1..7, 0 = none) u8 -- then the payload. A request whose counter
repeats the previous one is a retransmission and is discarded; the counter memory is cleared when the slave goes
back to INIT. Replies carry the slave's own counter, 1..7, unrelated to the requests'.

CoE payload: header u16 (bits 12-15 service: 2 SDO request, 3 SDO response, 8 SDO information), then for SDO a
command byte, index u16, subindex u8 and 4 data bytes (the minimum message is 10 bytes). Command bytes, as SOEM
sends and checks them:

- download expedited 0x23 | (4 - size) << 2; answer 0x60;
- download normal 0x21 with the complete size u32, data after it; answer 0x60; then segments
  ``toggle | (7 - n) << 1 | last`` with up to mailbox size - 3 data bytes each, answered 0x20 | toggle;
- upload 0x40; answer expedited 0x43 | (4 - size) << 2 when the value fits 4 bytes, otherwise normal 0x41 with the
  size u32 and as much data as fits (mailbox size - 16); SOEM then asks for segments with 0x60 | toggle, answered
  ``toggle | (7 - n) << 1 | last`` with data from byte 3 of the CoE payload;
- abort 0x80 with the abort code u32, sent with the SDO request service (2) as ETG.1000.6 specifies and SOEM
  expects; complete access (bit 4 of 0x21/0x40) is not offered.

SDO information (service 8; what SOEM's ``slaveinfo -sdo`` and pysoem's ``slave.od`` read): opcode u8 (bit 7 = more
fragments follow), reserved u8, fragments still to come u16, then data. Object list 0x01 -> 0x02 (list type u16 in
the first fragment, then the indices u16, split over as many messages as the mailbox needs, counting the fragments
down to 0); object description 0x03 -> 0x04 (index, data type u16, highest subindex u8, object code u8, name); entry
description 0x05 -> 0x06 (index, subindex, value info u8, data type u16, bit length u16, access u16, name); an unknown
object or entry answers 0x07 with the abort code u32.

The quirk profiles (``quirks.py``) change only what the specification leaves open or what real slaves are seen to
do: reserved bits, the reply counter, which legal encoding an upload takes, the service an abort travels under,
emergencies between replies.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from humanoid_prime.drivers.ethercat.wire import (
    ABORT_COMMAND,
    ABORT_LENGTH,
    ABORT_TOGGLE,
    ABORT_UNSUPPORTED_ACCESS,
    CCS_DOWNLOAD,
    CCS_DOWNLOAD_SEGMENT,
    CCS_UPLOAD,
    CCS_UPLOAD_SEGMENT,
    COE_EMERGENCY,
    COE_SDO_INFO,
    COE_SDO_REQUEST,
    COE_SDO_RESPONSE,
    COE_SERVICE_SHIFT,
    CS_ABORT,
    INFO_ENTRY_REQUEST,
    INFO_ENTRY_RESPONSE,
    INFO_ERROR,
    INFO_LIST_ALL,
    INFO_LIST_RX_PDO,
    INFO_LIST_TX_PDO,
    INFO_OBJECT_REQUEST,
    INFO_OBJECT_RESPONSE,
    INFO_OD_LIST_REQUEST,
    INFO_OD_LIST_RESPONSE,
    MAILBOX_COUNTER_MASK,
    MAILBOX_COUNTER_SHIFT,
    MAILBOX_ERROR_INVALID_SIZE,
    MAILBOX_ERROR_SERVICE_NOT_SUPPORTED,
    MAILBOX_ERROR_UNSUPPORTED_PROTOCOL,
    MAILBOX_HEADER,
    MAILBOX_HEADER_SIZE,
    MAILBOX_TYPE_COE,
    MAILBOX_TYPE_ERROR,
    MAILBOX_TYPE_MASK,
    SDO_ABORT,
    SDO_COMPLETE_ACCESS,
    SDO_DOWNLOAD_RESPONSE,
    SDO_DOWNLOAD_SEGMENT_RESPONSE,
    SDO_EXPEDITED,
    SDO_HEADER,
    SDO_INFO_HEADER,
    SDO_INFO_INCOMPLETE,
    SDO_LAST_SEGMENT,
    SDO_MIN_LENGTH,
    SDO_SEGMENT_DATA,
    SDO_SEGMENT_UNUSED_SHIFT,
    SDO_SIZE_INDICATED,
    SDO_TOGGLE,
    SDO_UPLOAD_RESPONSE,
    command_specifier,
    expedited_size,
    mailbox_message,
    sdo_upload_expedited,
)
from humanoid_prime.virtual.ring.od import DATA_TYPES, PDO_RX, PDO_TX, ObjectDictionary, SdoAbort
from humanoid_prime.virtual.ring.quirks import EMERGENCY_EVERY, NO_QUIRKS, Quirks

RESERVED_UPLOAD_BIT = 0x10  # bit 4 of an upload initiate reply: reserved
REQUEST_LOW_BITS = 0x1F  # what KickCAT's stack leaves of the request in its reply: everything below the specifier

# A write the server executed: (index, subindex, data). Kept by the caller for logs.
DownloadHook = Callable[[int, int, bytes], None]


class CoeServer:
    """Answers mailbox requests from an object dictionary. ``handle`` takes one complete mailbox message
    (header included) and returns the reply messages, in order (none when nothing is to be answered; more
    than one for a fragmented SDO information reply, or an emergency ahead of a reply)."""

    def __init__(self, od: ObjectDictionary, mailbox_size: int, on_download: DownloadHook | None = None, *,
                 quirks: Quirks = NO_QUIRKS, first_counter: int = 0) -> None:
        if mailbox_size < MAILBOX_HEADER_SIZE + SDO_MIN_LENGTH:
            raise ValueError(f"mailbox of {mailbox_size} bytes cannot hold an SDO (needs 16)")
        self.od = od
        self.mailbox_size = mailbox_size
        self.on_download = on_download
        self.quirks = quirks
        self.emergencies = 0
        self._last_counter = 0
        self._reply_counter = first_counter % 7  # the next reply carries this + 1
        self._replies_counted = 0
        self._replies = 0
        self._upload: tuple[int, int, bytes, int, int] | None = None  # index, sub, data, sent, toggle
        self._download: tuple[int, int, bytearray, int, int] | None = None  # index, sub, data, size, toggle

    def reset(self) -> None:
        """Forget transfers in progress and the last counter (the slave went back to INIT)."""
        self._last_counter = 0
        self._upload = None
        self._download = None

    def handle(self, message: bytes) -> list[bytes]:
        if len(message) < MAILBOX_HEADER_SIZE:
            return [self._mailbox_error(MAILBOX_ERROR_INVALID_SIZE)]
        length, _address, _channel, type_counter = MAILBOX_HEADER.unpack_from(message)
        counter = (type_counter >> MAILBOX_COUNTER_SHIFT) & MAILBOX_COUNTER_MASK
        if counter and counter == self._last_counter and "counter" not in self.quirks:
            return []
        self._last_counter = counter
        payload = bytes(message[MAILBOX_HEADER_SIZE:MAILBOX_HEADER_SIZE + length])
        if len(payload) < length:
            return [self._mailbox_error(MAILBOX_ERROR_INVALID_SIZE)]
        if type_counter & MAILBOX_TYPE_MASK != MAILBOX_TYPE_COE:
            return [self._mailbox_error(MAILBOX_ERROR_UNSUPPORTED_PROTOCOL)]
        if len(payload) < 2:
            return [self._mailbox_error(MAILBOX_ERROR_INVALID_SIZE)]
        service = struct.unpack_from("<H", payload)[0] >> COE_SERVICE_SHIFT
        if service == COE_SDO_INFO and len(payload) >= SDO_INFO_HEADER.size:
            return [self._reply(reply) for reply in self._info(payload)]
        if service != COE_SDO_REQUEST:
            return [self._mailbox_error(MAILBOX_ERROR_SERVICE_NOT_SUPPORTED)]
        if len(payload) < SDO_MIN_LENGTH:
            return [self._mailbox_error(MAILBOX_ERROR_INVALID_SIZE)]
        reply = self._sdo(payload)
        if reply is None:
            return []
        replies = [self._reply(reply)]
        self._replies += 1
        if "emergency" in self.quirks and self._replies % EMERGENCY_EVERY == 0:
            self.emergencies += 1
            replies.insert(0, self._reply(_emergency(0x0000)))  # 0x0000: error reset or no error (CiA 301)
        return replies

    def _next_counter(self) -> int:
        self._replies_counted += 1
        if "counter" not in self.quirks or self._replies_counted % 2:  # that profile moves on every other reply
            self._reply_counter = self._reply_counter % 7 + 1
        return self._reply_counter

    def _reply(self, payload: bytes) -> bytes:
        return mailbox_message(payload, MAILBOX_TYPE_COE, self._next_counter())

    def _mailbox_error(self, detail: int) -> bytes:
        return mailbox_message(struct.pack("<HH", 0x0001, detail), MAILBOX_TYPE_ERROR, self._next_counter())

    # ---- SDO information ----------------------------------------------------------------------------------
    def _info(self, payload: bytes) -> list[bytes]:
        opcode = payload[2] & ~SDO_INFO_INCOMPLETE & 0xFF
        data = payload[SDO_INFO_HEADER.size:]
        try:
            if opcode == INFO_OD_LIST_REQUEST and len(data) >= 2:
                return self._od_list(struct.unpack_from("<H", data)[0])
            if opcode == INFO_OBJECT_REQUEST and len(data) >= 2:
                index = struct.unpack_from("<H", data)[0]
                name, code, data_type, max_sub = self.od.describe(index)
                return [_info_frame(INFO_OBJECT_RESPONSE, 0, struct.pack("<HHBB", index, data_type, max_sub, code)
                                    + name.encode("ascii"))]
            if opcode == INFO_ENTRY_REQUEST and len(data) >= 4:
                index, sub, value_info = struct.unpack_from("<HBB", data)
                entry = self.od.entry(index, sub)
                described = struct.pack("<HBBHHH", index, sub, value_info & 0x07, DATA_TYPES[entry.fmt], entry.bits,
                                        entry.access_bits)
                return [_info_frame(INFO_ENTRY_RESPONSE, 0, described + entry.name.encode("ascii"))]
            raise SdoAbort(ABORT_COMMAND, f"SDO information opcode 0x{opcode:02X}")
        except SdoAbort as abort:
            return [_info_frame(INFO_ERROR, 0, struct.pack("<I", abort.code))]

    def _od_list(self, list_type: int) -> list[bytes]:
        """The object list, the list type first, in as many fragments as the mailbox needs."""
        if list_type == INFO_LIST_ALL:
            indices = self.od.indices
        elif list_type in (INFO_LIST_RX_PDO, INFO_LIST_TX_PDO):
            want = PDO_RX if list_type == INFO_LIST_RX_PDO else PDO_TX
            indices = [i for i in self.od.indices if any(e.pdo == want for e in self.od.subs(i))]
        else:  # backup and settings objects: this drive keeps none
            indices = []
        words = [list_type, *indices]
        per_message = (self.mailbox_size - MAILBOX_HEADER_SIZE - SDO_INFO_HEADER.size) // 2
        chunks = [words[k:k + per_message] for k in range(0, len(words), per_message)]
        return [_info_frame(INFO_OD_LIST_RESPONSE, len(chunks) - 1 - n, struct.pack(f"<{len(chunk)}H", *chunk))
                for n, chunk in enumerate(chunks)]

    # ---- SDO ----------------------------------------------------------------------------------------------
    def _sdo(self, payload: bytes) -> bytes | None:
        _coe, command, index, sub = SDO_HEADER.unpack_from(payload)
        specifier = command_specifier(command)
        if specifier in (CCS_DOWNLOAD_SEGMENT, CCS_UPLOAD_SEGMENT):  # segments carry no address; an abort names
            transfer = self._download if specifier == CCS_DOWNLOAD_SEGMENT else self._upload  # the transfer's object
            if transfer is not None:
                index, sub = transfer[0], transfer[1]
        try:
            if specifier == CCS_DOWNLOAD:
                self._upload = None
                return self._download_initiate(command, index, sub, payload)
            if specifier == CCS_DOWNLOAD_SEGMENT:
                return self._download_segment(command, payload)
            if specifier == CCS_UPLOAD:
                self._download = None
                return self._upload_initiate(command, index, sub)
            if specifier == CCS_UPLOAD_SEGMENT:
                return self._upload_segment(command)
            if specifier == CS_ABORT:  # the master aborts: drop the transfer, nothing to answer
                self._upload = None
                self._download = None
                return None
            raise SdoAbort(ABORT_COMMAND, f"command 0x{command:02X}")
        except SdoAbort as abort:
            self._upload = None
            self._download = None
            # an abort travels as an SDO request (ETG.1000.6); SOES sent it as a response (SOES #115)
            service = COE_SDO_RESPONSE if "abort-service" in self.quirks else COE_SDO_REQUEST
            return _sdo_frame(self._reserved(SDO_ABORT, command), index, sub, struct.pack("<I", abort.code), service)

    def _reserved(self, reply: int, request: int) -> int:
        """``reply`` with the request's low bits left in it where the quirk profile says so (they are reserved)."""
        return reply | (request & REQUEST_LOW_BITS) if "reserved-bits" in self.quirks else reply

    def _download_initiate(self, command: int, index: int, sub: int, payload: bytes) -> bytes:
        if command & SDO_COMPLETE_ACCESS:
            raise SdoAbort(ABORT_UNSUPPORTED_ACCESS, "complete access is not supported")
        answer = self._reserved(SDO_DOWNLOAD_RESPONSE, command)
        if command & SDO_EXPEDITED:
            self._store(index, sub, payload[6:6 + expedited_size(command)])
            return _sdo_frame(answer, index, sub)
        total = struct.unpack_from("<I", payload, 6)[0]
        data = payload[10:]
        if len(data) >= total:
            self._store(index, sub, data[:total])
            return _sdo_frame(answer, index, sub)
        self.od.entry(index, sub)  # fail early for a missing object, before segments arrive
        self._download = (index, sub, bytearray(data), total, 0)
        return _sdo_frame(answer, index, sub)

    def _download_segment(self, command: int, payload: bytes) -> bytes:
        if self._download is None:
            raise SdoAbort(ABORT_COMMAND, "download segment without a download in progress")
        index, sub, data, total, toggle = self._download
        if command & SDO_TOGGLE != toggle:
            raise SdoAbort(ABORT_TOGGLE)
        # a minimum-size segment says in bits 1-3 how many of its 7 data bytes are unused
        if len(payload) == SDO_MIN_LENGTH:
            data += payload[3:3 + SDO_SEGMENT_DATA - ((command >> SDO_SEGMENT_UNUSED_SHIFT) & 0x07)]
        else:
            data += payload[3:]
        if command & SDO_LAST_SEGMENT:
            self._download = None
            if len(data) != total:
                raise SdoAbort(ABORT_LENGTH, f"announced {total} bytes, received {len(data)}")
            self._store(index, sub, bytes(data))
        else:
            self._download = (index, sub, data, total, toggle ^ SDO_TOGGLE)
        reserved = command & 0x0F if "reserved-bits" in self.quirks else 0  # bits 0-3 of this reply are reserved
        return struct.pack("<HB", COE_SDO_RESPONSE << COE_SERVICE_SHIFT,
                           SDO_DOWNLOAD_SEGMENT_RESPONSE | toggle | reserved) + b"\x00" * 7

    def _store(self, index: int, sub: int, data: bytes) -> None:
        self.od.download(index, sub, data)
        if self.on_download is not None:
            self.on_download(index, sub, data)

    def _upload_initiate(self, command: int, index: int, sub: int) -> bytes:
        if command & SDO_COMPLETE_ACCESS:
            raise SdoAbort(ABORT_UNSUPPORTED_ACCESS, "complete access is not supported")
        data = self.od.upload(index, sub)
        reserved = RESERVED_UPLOAD_BIT if "reserved-bits" in self.quirks else 0
        normal = SDO_UPLOAD_RESPONSE | SDO_SIZE_INDICATED | reserved  # e = 0: the size u32, then the data
        if len(data) == 4 and "normal-upload" in self.quirks:
            return _sdo_frame(normal, index, sub, struct.pack("<I", 4) + data)
        if 0 < len(data) <= 4:
            padded = data.ljust(4, b"\x00")
            if "no-size" in self.quirks and len(data) == 4:  # e = 1, s = 0: four data bytes, their number unsaid
                return _sdo_frame(SDO_UPLOAD_RESPONSE | SDO_EXPEDITED | reserved, index, sub, padded)
            return _sdo_frame(sdo_upload_expedited(len(data)) | reserved, index, sub, padded)
        room = self.mailbox_size - MAILBOX_HEADER_SIZE - SDO_MIN_LENGTH
        first = data[:room]
        if len(first) < len(data):
            self._upload = (index, sub, data, len(first), 0)
        return _sdo_frame(normal, index, sub, struct.pack("<I", len(data)) + first)

    def _upload_segment(self, command: int) -> bytes:
        if self._upload is None:
            raise SdoAbort(ABORT_COMMAND, "upload segment without an upload in progress")
        index, sub, data, sent, toggle = self._upload
        if command & SDO_TOGGLE != toggle:
            raise SdoAbort(ABORT_TOGGLE)
        room = self.mailbox_size - MAILBOX_HEADER_SIZE - 3
        chunk = data[sent:sent + room]
        sent += len(chunk)
        last = sent >= len(data)
        self._upload = None if last else (index, sub, data, sent, toggle ^ SDO_TOGGLE)
        unused = SDO_SEGMENT_DATA - len(chunk) if len(chunk) < SDO_SEGMENT_DATA else 0
        head = struct.pack("<HB", COE_SDO_RESPONSE << COE_SERVICE_SHIFT,
                           toggle | (unused << SDO_SEGMENT_UNUSED_SHIFT) | int(last))
        return head + chunk + b"\x00" * unused


def _sdo_frame(command: int, index: int, sub: int, data: bytes = b"\x00\x00\x00\x00",
               service: int = COE_SDO_RESPONSE) -> bytes:
    return SDO_HEADER.pack(service << COE_SERVICE_SHIFT, command, index, sub) + data


def _emergency(code: int) -> bytes:
    """A CoE emergency: error code u16, error register u8, five manufacturer bytes."""
    return struct.pack("<HHB5x", COE_EMERGENCY << COE_SERVICE_SHIFT, code, 0)


def _info_frame(opcode: int, fragments_left: int, data: bytes) -> bytes:
    incomplete = SDO_INFO_INCOMPLETE if fragments_left else 0x00
    return SDO_INFO_HEADER.pack(COE_SDO_INFO << COE_SERVICE_SHIFT, opcode | incomplete, 0, fragments_left) + data


def sdo_abort_code(reply: bytes) -> int | None:
    """The abort code of a CoE reply message, or None if it is not an abort (for tests and tools)."""
    if len(reply) < MAILBOX_HEADER_SIZE + SDO_MIN_LENGTH:
        return None
    if command_specifier(reply[MAILBOX_HEADER_SIZE + 2]) != CS_ABORT:
        return None
    return struct.unpack_from("<I", reply, MAILBOX_HEADER_SIZE + 6)[0]
