"""CoE SDO server: the request and reply bytes SOEM's ecx_SDOread / ecx_SDOwrite exchange."""

from __future__ import annotations

import struct

import pytest

from humanoid_prime.virtual.ring.drive import FACTORY_POS_REG, ErobDrive
from humanoid_prime.virtual.ring.mailbox import CoeServer, mailbox_message, sdo_abort_code
from humanoid_prime.virtual.ring.od import (
    ABORT_LENGTH,
    ABORT_NO_OBJECT,
    ABORT_NO_SUBINDEX,
    ABORT_READ_ONLY,
    ABORT_TOGGLE,
    ABORT_UNSUPPORTED_ACCESS,
    ABORT_VALUE_RANGE,
    READ_ONLY,
    Entry,
)

LONG_TEXT = "".join(chr(ord("a") + i % 26) for i in range(300))
MAILBOX = 128


class Session:
    """Builds requests the way SOEM does (CoE header 0x2000, counter 1..7) and unpacks the replies."""

    def __init__(self, server: CoeServer) -> None:
        self.server = server
        self.counter = 0

    def send(self, payload: bytes) -> bytes:
        self.counter = self.counter % 7 + 1
        reply = self.server.handle(mailbox_message(payload, 3, self.counter))
        assert reply is not None
        return reply

    @staticmethod
    def sdo(command: int, index: int, sub: int, data: bytes = bytes(4)) -> bytes:
        return struct.pack("<HBHB", 0x2000, command, index, sub) + data

    def upload(self, index: int, sub: int) -> bytes:
        reply = self.send(self.sdo(0x40, index, sub))
        command = reply[8]
        if command & 0x02:
            return reply[12:12 + 4 - ((command >> 2) & 3)]
        size = struct.unpack_from("<I", reply, 12)[0]
        length = struct.unpack_from("<H", reply)[0]
        data = bytearray(reply[16:6 + length])
        toggle = 0
        while len(data) < size:
            segment = self.send(self.sdo(0x60 | toggle, 0, 0))
            assert segment[8] & 0xE0 == 0x00 and segment[8] & 0x10 == toggle
            length = struct.unpack_from("<H", segment)[0] - 3
            if length == 7:
                length -= (segment[8] >> 1) & 0x07
            data += segment[9:9 + length]
            toggle ^= 0x10
        return bytes(data)

    def download_expedited(self, index: int, sub: int, data: bytes) -> bytes:
        return self.send(self.sdo(0x23 | ((4 - len(data)) << 2), index, sub, data.ljust(4, b"\x00")))


@pytest.fixture
def drive() -> ErobDrive:
    drive = ErobDrive(serial=7)
    drive.od.add(Entry(0x2100, 0, "long text", "s", LONG_TEXT, READ_ONLY))
    return drive


@pytest.fixture
def session(drive) -> Session:
    return Session(CoeServer(drive.od, MAILBOX))


def test_expedited_upload_returns_the_value_and_its_size(session):
    reply = session.send(Session.sdo(0x40, 0x1018, 1))
    assert reply[6:8] == b"\x00\x30"  # CoE SDO response
    assert reply[8] == 0x43  # expedited, size indicated, 4 bytes
    assert struct.unpack_from("<I", reply, 12)[0] == 0x5A65726F


def test_expedited_upload_of_a_u8_says_three_bytes_unused(session):
    reply = session.send(Session.sdo(0x40, 0x1C00, 0))
    assert reply[8] == 0x4F
    assert reply[12] == 4


def test_normal_upload_of_a_string_that_fits_the_mailbox(session):
    assert session.upload(0x1008, 0) == b"eRob rotary actuator, CiA402 (emulated)"


def test_segmented_upload_reassembles_a_long_object(session):
    assert session.upload(0x2100, 0) == LONG_TEXT.encode()


def test_first_upload_reply_carries_the_complete_size(session):
    reply = session.send(Session.sdo(0x40, 0x2100, 0))
    assert reply[8] == 0x41
    assert struct.unpack_from("<I", reply, 12)[0] == 300
    assert struct.unpack_from("<H", reply)[0] == MAILBOX - 6  # initial reply fills the mailbox


def test_segment_with_wrong_toggle_is_aborted(session):
    session.send(Session.sdo(0x40, 0x2100, 0))
    reply = session.send(Session.sdo(0x70, 0, 0))  # toggle 1 where 0 is due
    assert sdo_abort_code(reply) == ABORT_TOGGLE
    assert struct.unpack_from("<HB", reply, 9) == (0x2100, 0)


def test_expedited_download_writes_the_object(session, drive):
    session.download_expedited(0x2383, 0, b"\x01")
    reply = session.download_expedited(0x2382, 1, struct.pack("<I", 600))
    assert reply[8] == 0x60
    assert drive.pos_reg.value == 600


def test_normal_and_segmented_download(session, drive):
    drive.od.add(Entry(0x2101, 0, "scratch", "s", ""))
    text = bytes(range(65, 91)) * 8  # 208 bytes: one initial and two segments in a 128-byte mailbox
    room = MAILBOX - 16
    session.send(struct.pack("<HBHBI", 0x2000, 0x21, 0x2101, 0, len(text)) + text[:room])
    rest, toggle = text[room:], 0
    while rest:
        chunk, rest = rest[:MAILBOX - 9], rest[MAILBOX - 9:]
        reply = session.send(struct.pack("<HB", 0x2000, toggle | (0 if rest else 1)) + chunk)
        assert reply[8] == 0x20 | toggle
        toggle ^= 0x10
    assert drive.od.value(0x2101, 0) == text.decode()


def test_short_last_download_segment_states_its_unused_bytes(session, drive):
    drive.od.add(Entry(0x2102, 0, "scratch", "s", ""))
    text = b"x" * (MAILBOX - 16) + b"abc"
    session.send(struct.pack("<HBHBI", 0x2000, 0x21, 0x2102, 0, len(text)) + text[:MAILBOX - 16])
    session.send(struct.pack("<HB", 0x2000, 0x01 | (4 << 1)) + b"abc" + bytes(4))
    assert drive.od.value(0x2102, 0).endswith("abc")


@pytest.mark.parametrize(("index", "sub", "code"), [(0x2999, 0, ABORT_NO_OBJECT), (0x1018, 9, ABORT_NO_SUBINDEX)])
def test_upload_of_a_missing_object_is_aborted(session, index, sub, code):
    reply = session.send(Session.sdo(0x40, index, sub))
    assert reply[6:8] == b"\x00\x20"  # an abort is sent with the SDO request service
    assert reply[8] == 0x80
    assert sdo_abort_code(reply) == code


def test_write_to_a_read_only_object_is_aborted(session):
    assert sdo_abort_code(session.download_expedited(0x6041, 0, b"\x00\x00")) == ABORT_READ_ONLY


def test_gate_value_outside_0_and_1_is_aborted(session):
    assert sdo_abort_code(session.download_expedited(0x2383, 0, b"\x02")) == ABORT_VALUE_RANGE


def test_wrong_length_is_aborted(session):
    assert sdo_abort_code(session.download_expedited(0x6040, 0, b"\x06\x00\x00")) == ABORT_LENGTH


def test_complete_access_is_refused(session):
    reply = session.send(Session.sdo(0x50, 0x1C12, 0))
    assert sdo_abort_code(reply) == ABORT_UNSUPPORTED_ACCESS


def test_repeated_mailbox_counter_is_discarded_as_a_retransmission(drive):
    server = CoeServer(drive.od, MAILBOX)
    request = mailbox_message(Session.sdo(0x40, 0x1018, 1), 3, 5)
    assert server.handle(request) is not None
    assert server.handle(request) is None


def test_counter_memory_is_cleared_by_reset(drive):
    server = CoeServer(drive.od, MAILBOX)
    request = mailbox_message(Session.sdo(0x40, 0x1018, 1), 3, 1)
    server.handle(request)
    server.reset()
    assert server.handle(request) is not None


def test_gain_write_with_gate_closed_succeeds_but_keeps_the_factory_value(session, drive):
    reply = session.download_expedited(0x2382, 1, struct.pack("<I", 600))
    assert reply[8] == 0x60
    assert struct.unpack("<I", session.upload(0x2382, 1))[0] == FACTORY_POS_REG


def test_non_sdo_service_gets_a_mailbox_error(session):
    reply = session.send(struct.pack("<HBBH", 0x8000, 0x01, 0, 0))  # SDO information request
    assert reply[5] & 0x0F == 0x00  # mailbox error type
    assert struct.unpack_from("<HH", reply, 6) == (0x0001, 0x0004)  # service not supported
