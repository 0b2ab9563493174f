"""The slave side of the EtherCAT mailbox and of CoE SDO transfers (ETG.1000.4 / ETG.1000.6).

Mailbox message: header of 6 bytes -- length u16 (bytes after the header), address u16, channel and
priority u8, type (bits 0-3; 3 = CoE) and counter (bits 4-6, 1..7, 0 = none) u8 -- then the payload.
A request whose counter repeats the previous one is a retransmission and is discarded; the counter
memory is cleared when the slave goes back to INIT.

CoE payload: header u16 (bits 12-15 service: 2 SDO request, 3 SDO response, 8 SDO information), then
for SDO a command byte, index u16, subindex u8 and 4 data bytes (the minimum message is 10 bytes).
Command bytes, as SOEM sends and checks them:

- download expedited 0x23 | (4 - size) << 2; answer 0x60;
- download normal 0x21 with the complete size u32, data after it; answer 0x60; then segments
  ``toggle | (7 - n) << 1 | last`` with up to mailbox size - 3 data bytes each, answered 0x20 | toggle;
- upload 0x40; answer expedited 0x43 | (4 - size) << 2 when the value fits 4 bytes, otherwise normal
  0x41 with the size u32 and as much data as fits (mailbox size - 16); SOEM then asks for segments
  with 0x60 | toggle, answered ``toggle | (7 - n) << 1 | last`` with data from byte 3 of the CoE payload;
- abort 0x80 with the abort code u32, sent with the SDO request service (2) as ETG.1000.6 specifies and
  SOEM expects; complete access (bit 4 of 0x21/0x40) is not offered.

SDO information (service 8; what SOEM's ``slaveinfo -sdo`` and pysoem's ``slave.od`` read): opcode u8
(bit 7 = more fragments follow), reserved u8, fragments still to come u16, then data. Object list 0x01 ->
0x02 (list type u16 in the first fragment, then the indices u16, split over as many messages as the
mailbox needs, counting the fragments down to 0); object description 0x03 -> 0x04 (index, data type u16,
highest subindex u8, object code u8, name); entry description 0x05 -> 0x06 (index, subindex, value info
u8, data type u16, bit length u16, access u16, name); an unknown object or entry answers 0x07 with the
abort code u32.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from humanoid_prime.virtual.ring.od import (
    ABORT_COMMAND,
    ABORT_LENGTH,
    ABORT_TOGGLE,
    ABORT_UNSUPPORTED_ACCESS,
    DATA_TYPES,
    PDO_RX,
    PDO_TX,
    ObjectDictionary,
    SdoAbort,
)

MAILBOX_HEADER_SIZE = 6
MAILBOX_TYPE_ERROR = 0x00
MAILBOX_TYPE_COE = 0x03
COE_SDO_REQUEST = 2
COE_SDO_RESPONSE = 3
COE_SDO_INFO = 8
INFO_OD_LIST_REQ, INFO_OD_LIST_RES = 0x01, 0x02
INFO_OD_REQ, INFO_OD_RES = 0x03, 0x04
INFO_OE_REQ, INFO_OE_RES = 0x05, 0x06
INFO_ERROR = 0x07
INFO_HEADER = struct.Struct("<HBBH")  # CoE header, opcode, reserved, fragments still to come
LIST_ALL, LIST_RX_PDO, LIST_TX_PDO = 0x01, 0x02, 0x03
SDO_MIN_LENGTH = 10
SDO_ABORT = 0x80  # CoE header 2 + command 1 + index 2 + subindex 1 + data 4
MAILBOX_ERROR_SERVICE_NOT_SUPPORTED = 0x0004
MAILBOX_ERROR_INVALID_SIZE = 0x0008
MAILBOX_ERROR_UNSUPPORTED_PROTOCOL = 0x0002

_HEADER = struct.Struct("<HHBB")
_SDO = struct.Struct("<HBHB")  # CoE header, command, index, subindex

# A write the server executed: (index, subindex, data). Kept by the caller for logs.
DownloadHook = Callable[[int, int, bytes], None]


def mailbox_message(payload: bytes, mailbox_type: int, counter: int) -> bytes:
    return _HEADER.pack(len(payload), 0, 0, (mailbox_type & 0x0F) | ((counter & 0x07) << 4)) + payload


def _sdo_frame(command: int, index: int, sub: int, data: bytes = b"\x00\x00\x00\x00") -> bytes:
    service = COE_SDO_REQUEST if command == SDO_ABORT else COE_SDO_RESPONSE  # an abort travels as a request
    return _SDO.pack(service << 12, command, index, sub) + data


class CoeServer:
    """Answers mailbox requests from an object dictionary. ``handle`` takes one complete mailbox message
    (header included) and returns the reply messages, in order (none when nothing is to be answered; more
    than one for a fragmented SDO information reply)."""

    def __init__(self, od: ObjectDictionary, mailbox_size: int, on_download: DownloadHook | None = None) -> None:
        if mailbox_size < MAILBOX_HEADER_SIZE + SDO_MIN_LENGTH:
            raise ValueError(f"mailbox of {mailbox_size} bytes cannot hold an SDO (needs 16)")
        self.od = od
        self.mailbox_size = mailbox_size
        self.on_download = on_download
        self._last_counter = 0
        self._reply_counter = 0
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
        length, _address, _channel, type_counter = _HEADER.unpack_from(message)
        counter = (type_counter >> 4) & 0x07
        if counter and counter == self._last_counter:
            return []
        self._last_counter = counter
        payload = bytes(message[MAILBOX_HEADER_SIZE:MAILBOX_HEADER_SIZE + length])
        if len(payload) < length:
            return [self._mailbox_error(MAILBOX_ERROR_INVALID_SIZE)]
        if type_counter & 0x0F != MAILBOX_TYPE_COE:
            return [self._mailbox_error(MAILBOX_ERROR_UNSUPPORTED_PROTOCOL)]
        if len(payload) < 2:
            return [self._mailbox_error(MAILBOX_ERROR_INVALID_SIZE)]
        service = struct.unpack_from("<H", payload)[0] >> 12
        if service == COE_SDO_INFO and len(payload) >= INFO_HEADER.size:
            return [self._reply(reply) for reply in self._info(payload)]
        if service != COE_SDO_REQUEST:
            return [self._mailbox_error(MAILBOX_ERROR_SERVICE_NOT_SUPPORTED)]
        if len(payload) < SDO_MIN_LENGTH:
            return [self._mailbox_error(MAILBOX_ERROR_INVALID_SIZE)]
        reply = self._sdo(payload)
        return [] if reply is None else [self._reply(reply)]

    def _next_counter(self) -> int:
        self._reply_counter = self._reply_counter % 7 + 1
        return self._reply_counter

    def _reply(self, payload: bytes) -> bytes:
        return mailbox_message(payload, MAILBOX_TYPE_COE, self._next_counter())

    def _mailbox_error(self, detail: int) -> bytes:
        return mailbox_message(struct.pack("<HH", 0x0001, detail), MAILBOX_TYPE_ERROR, self._next_counter())

    # ---- SDO information ----------------------------------------------------------------------------------
    def _info(self, payload: bytes) -> list[bytes]:
        opcode = payload[2] & 0x7F
        data = payload[INFO_HEADER.size:]
        try:
            if opcode == INFO_OD_LIST_REQ and len(data) >= 2:
                return self._od_list(struct.unpack_from("<H", data)[0])
            if opcode == INFO_OD_REQ and len(data) >= 2:
                index = struct.unpack_from("<H", data)[0]
                name, code, data_type, max_sub = self.od.describe(index)
                return [_info_frame(INFO_OD_RES, 0, struct.pack("<HHBB", index, data_type, max_sub, code)
                                    + name.encode("ascii"))]
            if opcode == INFO_OE_REQ and len(data) >= 4:
                index, sub, value_info = struct.unpack_from("<HBB", data)
                entry = self.od.entry(index, sub)
                described = struct.pack("<HBBHHH", index, sub, value_info & 0x07, DATA_TYPES[entry.fmt], entry.bits,
                                        entry.access_bits)
                return [_info_frame(INFO_OE_RES, 0, described + entry.name.encode("ascii"))]
            raise SdoAbort(ABORT_COMMAND, f"SDO information opcode 0x{opcode:02X}")
        except SdoAbort as abort:
            return [_info_frame(INFO_ERROR, 0, struct.pack("<I", abort.code))]

    def _od_list(self, list_type: int) -> list[bytes]:
        """The object list, the list type first, in as many fragments as the mailbox needs."""
        if list_type == LIST_ALL:
            indices = self.od.indices
        elif list_type in (LIST_RX_PDO, LIST_TX_PDO):
            want = PDO_RX if list_type == LIST_RX_PDO else PDO_TX
            indices = [i for i in self.od.indices if any(e.pdo == want for e in self.od.subs(i))]
        else:  # backup and settings objects: this drive keeps none
            indices = []
        words = [list_type, *indices]
        per_message = (self.mailbox_size - MAILBOX_HEADER_SIZE - INFO_HEADER.size) // 2
        chunks = [words[k:k + per_message] for k in range(0, len(words), per_message)]
        return [_info_frame(INFO_OD_LIST_RES, len(chunks) - 1 - n, struct.pack(f"<{len(chunk)}H", *chunk))
                for n, chunk in enumerate(chunks)]

    def _sdo(self, payload: bytes) -> bytes | None:
        _coe, command, index, sub = _SDO.unpack_from(payload)
        specifier = command >> 5
        if specifier in (0, 3):  # segments carry no address; an abort names the transfer's object
            transfer = self._download if specifier == 0 else self._upload
            if transfer is not None:
                index, sub = transfer[0], transfer[1]
        try:
            if specifier == 1:
                self._upload = None
                return self._download_initiate(command, index, sub, payload)
            if specifier == 0:
                return self._download_segment(command, payload)
            if specifier == 2:
                self._download = None
                return self._upload_initiate(command, index, sub)
            if specifier == 3:
                return self._upload_segment(command)
            if specifier == 4:  # the master aborts: drop the transfer, nothing to answer
                self._upload = None
                self._download = None
                return None
            raise SdoAbort(ABORT_COMMAND, f"command 0x{command:02X}")
        except SdoAbort as abort:
            self._upload = None
            self._download = None
            return _sdo_frame(SDO_ABORT, index, sub, struct.pack("<I", abort.code))

    def _download_initiate(self, command: int, index: int, sub: int, payload: bytes) -> bytes:
        if command & 0x10:
            raise SdoAbort(ABORT_UNSUPPORTED_ACCESS, "complete access is not supported")
        if command & 0x02:  # expedited
            size = 4 - ((command >> 2) & 0x03) if command & 0x01 else 4
            self._store(index, sub, payload[6:6 + size])
            return _sdo_frame(0x60, index, sub)
        total = struct.unpack_from("<I", payload, 6)[0]
        data = payload[10:]
        if len(data) >= total:
            self._store(index, sub, data[:total])
            return _sdo_frame(0x60, index, sub)
        self.od.entry(index, sub)  # fail early for a missing object, before segments arrive
        self._download = (index, sub, bytearray(data), total, 0)
        return _sdo_frame(0x60, index, sub)

    def _download_segment(self, command: int, payload: bytes) -> bytes:
        if self._download is None:
            raise SdoAbort(ABORT_COMMAND, "download segment without a download in progress")
        index, sub, data, total, toggle = self._download
        if command & 0x10 != toggle:
            raise SdoAbort(ABORT_TOGGLE)
        # a minimum-size segment says in bits 1-3 how many of its 7 data bytes are unused
        data += payload[3:3 + 7 - ((command >> 1) & 0x07)] if len(payload) == SDO_MIN_LENGTH else payload[3:]
        if command & 0x01:  # last segment
            self._download = None
            if len(data) != total:
                raise SdoAbort(ABORT_LENGTH, f"announced {total} bytes, received {len(data)}")
            self._store(index, sub, bytes(data))
        else:
            self._download = (index, sub, data, total, toggle ^ 0x10)
        return struct.pack("<HB", COE_SDO_RESPONSE << 12, 0x20 | toggle) + b"\x00" * 7

    def _store(self, index: int, sub: int, data: bytes) -> None:
        self.od.download(index, sub, data)
        if self.on_download is not None:
            self.on_download(index, sub, data)

    def _upload_initiate(self, command: int, index: int, sub: int) -> bytes:
        if command & 0x10:
            raise SdoAbort(ABORT_UNSUPPORTED_ACCESS, "complete access is not supported")
        data = self.od.upload(index, sub)
        if 0 < len(data) <= 4:
            padded = data + b"\x00" * (4 - len(data))
            return _sdo_frame(0x43 | ((4 - len(data)) << 2), index, sub, padded)
        room = self.mailbox_size - MAILBOX_HEADER_SIZE - SDO_MIN_LENGTH
        first = data[:room]
        if len(first) < len(data):
            self._upload = (index, sub, data, len(first), 0)
        return _sdo_frame(0x41, index, sub, struct.pack("<I", len(data)) + first)

    def _upload_segment(self, command: int) -> bytes:
        if self._upload is None:
            raise SdoAbort(ABORT_COMMAND, "upload segment without an upload in progress")
        index, sub, data, sent, toggle = self._upload
        if command & 0x10 != toggle:
            raise SdoAbort(ABORT_TOGGLE)
        room = self.mailbox_size - MAILBOX_HEADER_SIZE - 3
        chunk = data[sent:sent + room]
        sent += len(chunk)
        last = sent >= len(data)
        self._upload = None if last else (index, sub, data, sent, toggle ^ 0x10)
        unused = 7 - len(chunk) if len(chunk) < 7 else 0
        head = struct.pack("<HB", COE_SDO_RESPONSE << 12, toggle | (unused << 1) | int(last))
        return head + chunk + b"\x00" * unused


def _info_frame(opcode: int, fragments_left: int, data: bytes) -> bytes:
    incomplete = 0x80 if fragments_left else 0x00
    return INFO_HEADER.pack(COE_SDO_INFO << 12, opcode | incomplete, 0, fragments_left) + data


def sdo_abort_code(reply: bytes) -> int | None:
    """The abort code of a CoE reply message, or None if it is not an abort (for tests and tools)."""
    if len(reply) < MAILBOX_HEADER_SIZE + SDO_MIN_LENGTH or reply[MAILBOX_HEADER_SIZE + 2] != SDO_ABORT:
        return None
    return struct.unpack_from("<I", reply, MAILBOX_HEADER_SIZE + 6)[0]

