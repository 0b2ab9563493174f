"""CoE SDO server: the request and reply bytes SOEM's ecx_SDOread / ecx_SDOwrite exchange."""

from __future__ import annotations

import struct

import pytest

from humanoid_prime.drivers.ethercat.wire import (
    ABORT_LENGTH,
    ABORT_NO_OBJECT,
    ABORT_NO_SUBINDEX,
    ABORT_READ_ONLY,
    ABORT_TOGGLE,
    ABORT_UNSUPPORTED_ACCESS,
    ABORT_VALUE_RANGE,
    mailbox_message,
)
from humanoid_prime.virtual.ring.drive import FACTORY_POS_REG, ErobDrive
from humanoid_prime.virtual.ring.mailbox import CoeServer, sdo_abort_code
from humanoid_prime.virtual.ring.od import READ_ONLY, Entry

LONG_TEXT = "".join(chr(ord("a") + i % 26) for i in range(300))
MAILBOX = 128


class Session:
    """Builds requests the way SOEM does (CoE header 0x2000, counter 1..7) and unpacks the replies."""

    def __init__(self, server: CoeServer) -> None:
        self.server = server
        self.counter = 0

    def send(self, payload: bytes) -> bytes:
        replies = self.send_all(payload)
        assert len(replies) == 1, replies
        return replies[0]

    def send_all(self, payload: bytes) -> list[bytes]:
        self.counter = self.counter % 7 + 1
        return self.server.handle(mailbox_message(payload, 3, self.counter))

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
def variant_drive() -> ErobDrive:
    return ErobDrive(serial=8, gain_bytes=4)


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
    session.download_expedited(0x2383, 0, struct.pack("<I", 1))
    reply = session.download_expedited(0x2382, 1, struct.pack("<H", 600))
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
    assert sdo_abort_code(session.download_expedited(0x2383, 0, struct.pack("<I", 2))) == ABORT_VALUE_RANGE


def test_wrong_length_is_aborted(session):
    assert sdo_abort_code(session.download_expedited(0x6040, 0, b"\x06\x00\x00")) == ABORT_LENGTH


def test_complete_access_is_refused(session):
    reply = session.send(Session.sdo(0x50, 0x1C12, 0))
    assert sdo_abort_code(reply) == ABORT_UNSUPPORTED_ACCESS


def test_repeated_mailbox_counter_is_discarded_as_a_retransmission(drive):
    server = CoeServer(drive.od, MAILBOX)
    request = mailbox_message(Session.sdo(0x40, 0x1018, 1), 3, 5)
    assert len(server.handle(request)) == 1
    assert server.handle(request) == []


def test_counter_memory_is_cleared_by_reset(drive):
    server = CoeServer(drive.od, MAILBOX)
    request = mailbox_message(Session.sdo(0x40, 0x1018, 1), 3, 1)
    server.handle(request)
    server.reset()
    assert len(server.handle(request)) == 1


def test_gain_write_with_gate_closed_succeeds_but_keeps_the_factory_value(session, drive):
    reply = session.download_expedited(0x2382, 1, struct.pack("<H", 600))
    assert reply[8] == 0x60
    assert struct.unpack("<H", session.upload(0x2382, 1))[0] == FACTORY_POS_REG


def test_non_sdo_service_gets_a_mailbox_error(session):
    reply = session.send(struct.pack("<H", 0x5000))  # CoE service 5 (RxPDO): not offered
    assert reply[5] & 0x0F == 0x00  # mailbox error type
    assert struct.unpack_from("<HH", reply, 6) == (0x0001, 0x0004)  # service not supported


# ---- SDO information (what SOEM's slaveinfo -sdo and pysoem's slave.od read) ----------------------------------

def info(session: Session, opcode: int, data: bytes) -> list[tuple[int, int, bytes]]:
    """(opcode with its incomplete bit, fragments left, data) of every reply message."""
    replies = session.send_all(struct.pack("<HBBH", 0x8000, opcode, 0, 0) + data)
    out = []
    for reply in replies:
        length = struct.unpack_from("<H", reply)[0]
        coe, op, _reserved, fragments = struct.unpack_from("<HBBH", reply, 6)
        assert coe >> 12 == 8
        out.append((op, fragments, reply[12:6 + length]))
    return out


def test_the_object_list_names_every_object_once_in_order(session, drive):
    (op, fragments, data), = info(session, 0x01, struct.pack("<H", 1))
    assert (op, fragments) == (0x02, 0)
    words = struct.unpack(f"<{len(data) // 2}H", data)
    assert words[0] == 1  # the list type comes back first
    assert list(words[1:]) == drive.od.indices
    assert {0x1000, 0x1018, 0x2381, 0x2382, 0x2383, 0x6076, 0x6502, 0x1600, 0x1A00} <= set(words[1:])


def test_a_long_object_list_comes_in_fragments_counted_down(drive):
    session = Session(CoeServer(drive.od, 32))  # room for 10 words per message
    replies = info(session, 0x01, struct.pack("<H", 1))
    assert len(replies) > 3
    assert [fragments for _, fragments, _ in replies] == list(range(len(replies) - 1, -1, -1))
    assert [op for op, _, _ in replies] == [0x82] * (len(replies) - 1) + [0x02]
    words = b"".join(data for _, _, data in replies)
    assert list(struct.unpack(f"<{len(words) // 2}H", words)) == [1, *drive.od.indices]


def test_the_pdo_mappable_lists_hold_the_objects_of_each_direction(session):
    rx = struct.unpack("<" + "H" * 20, info(session, 0x01, struct.pack("<H", 2))[0][2].ljust(40, b"\0"))
    tx = struct.unpack("<" + "H" * 20, info(session, 0x01, struct.pack("<H", 3))[0][2].ljust(40, b"\0"))
    assert {0x6040, 0x607A, 0x60B1, 0x60B2, 0x6060} <= set(rx) and 0x6041 not in rx
    assert {0x6041, 0x6064, 0x606C, 0x6077, 0x603F, 0x6061, 0x6076} <= set(tx) and 0x6040 not in tx


def test_object_description_of_a_gain_array_as_the_eds_declares_it(session):
    (op, _, data), = info(session, 0x03, struct.pack("<H", 0x2382))
    index, data_type, max_sub, code = struct.unpack_from("<HHBB", data)
    assert (op, index, data_type, max_sub, code) == (0x04, 0x2382, 0x0006, 2, 0x08)  # ARRAY of UNSIGNED16
    assert data[6:] == b"Position Loop Gains"


def test_object_description_of_a_variable(session):
    (_, _, data), = info(session, 0x03, struct.pack("<H", 0x6076))
    assert struct.unpack_from("<HHBB", data) == (0x6076, 0x0007, 0, 0x07)  # VAR, UNSIGNED32


def test_entry_description_gives_type_size_access_and_name(session):
    (op, _, data), = info(session, 0x05, struct.pack("<HBB", 0x2381, 1, 0x07))
    assert op == 0x06
    assert struct.unpack_from("<HBBHHH", data) == (0x2381, 1, 0x07, 0x0006, 16, 0x003F)  # rw, not mappable
    assert data[10:] == b"Velocity Loop Proportional Gain"
    (_, _, data), = info(session, 0x05, struct.pack("<HBB", 0x6064, 0, 0x07))
    assert struct.unpack_from("<HBBHHH", data)[3:] == (0x0004, 32, 0x0087)  # INTEGER32, ro, TxPDO mappable


def test_the_u32_variant_describes_its_gains_as_unsigned32(variant_drive):
    session = Session(CoeServer(variant_drive.od, MAILBOX))
    (_, _, data), = info(session, 0x05, struct.pack("<HBB", 0x2382, 1, 0x07))
    assert struct.unpack_from("<HBBHHH", data)[3:5] == (0x0007, 32)


@pytest.mark.parametrize("opcode, data, code", [
    (0x03, struct.pack("<H", 0x2999), 0x06020000),
    (0x05, struct.pack("<HBB", 0x2382, 9, 7), 0x06090011),
    (0x05, struct.pack("<HBB", 0x2999, 0, 7), 0x06020000),
    (0x09, b"", 0x05040001),
])
def test_an_unknown_object_or_entry_is_an_information_error(session, opcode, data, code):
    (op, _, reply), = info(session, opcode, data)
    assert (op, struct.unpack("<I", reply)[0]) == (0x07, code)
