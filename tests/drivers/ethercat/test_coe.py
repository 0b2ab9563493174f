"""CoE replies as Prime's mailbox reads them: matched on what identifies them, every legal encoding taken, reserved
bits and the slave's counter ignored, and each reply that answers no request named for what it was."""

from __future__ import annotations

import struct

from hypothesis import given
from hypothesis import strategies as st

from humanoid_prime.drivers.ethercat.coe import (
    ABORT,
    EMERGENCY,
    LATE,
    MAILBOX_ERROR,
    MALFORMED,
    OTHER_OBJECT,
    SDO,
    UNRECOGNISED,
    Expected,
    read_message,
    segment_data,
    upload_value,
    why_dropped,
)
from humanoid_prime.drivers.ethercat.wire import SCS_DOWNLOAD, SCS_UPLOAD, SCS_UPLOAD_SEGMENT, mailbox_message

DOWNLOAD = Expected(SCS_DOWNLOAD, 0x1C12, 0)
UPLOAD = Expected(SCS_UPLOAD, 0x6076, 0)
counters = st.integers(0, 7)


def coe(service: int, command: int, index: int = 0, sub: int = 0, data: bytes = bytes(4), counter: int = 1) -> bytes:
    return mailbox_message(struct.pack("<HBHB", service << 12, command, index, sub) + data, 0x03, counter)


@given(low=st.integers(0, 0x1F), counter=counters)
def test_a_download_reply_is_the_top_three_bits_whatever_the_reserved_bits_and_counter(low, counter):
    reply = read_message(coe(3, 0x60 | low, 0x1C12, 0, counter=counter))
    assert DOWNLOAD.answered_by(reply)


def test_the_replies_kickcat_s_stack_sends_are_taken():
    # it answers in the request's own buffer and rewrites only the specifier: 0x2F -> 0x6F, 0x23 -> 0x63, 0x2B -> 0x6B
    for command in (0x6F, 0x63, 0x6B):
        assert DOWNLOAD.answered_by(read_message(coe(3, command, 0x1C12, 0)))


@given(size=st.integers(1, 4), reserved=st.sampled_from([0x00, 0x10]), counter=counters,
       value=st.binary(min_size=4, max_size=4))
def test_an_expedited_upload_with_its_size_gives_that_many_bytes(size, reserved, counter, value):
    reply = read_message(coe(3, 0x43 | (4 - size) << 2 | reserved, 0x6076, 0, value, counter))
    assert UPLOAD.answered_by(reply)
    assert upload_value(reply) == (value[:size], size)


def test_an_expedited_upload_without_a_size_gives_all_four_bytes():
    reply = read_message(coe(3, 0x42, 0x6076, 0, struct.pack("<I", 23000)))
    assert UPLOAD.answered_by(reply) and upload_value(reply) == (struct.pack("<I", 23000), 4)


def test_a_four_byte_value_as_a_normal_upload_gives_the_same_bytes():
    reply = read_message(coe(3, 0x41, 0x6076, 0, struct.pack("<II", 4, 23000)))
    assert UPLOAD.answered_by(reply) and upload_value(reply) == (struct.pack("<I", 23000), 4)


def test_a_normal_upload_longer_than_its_message_says_how_much_is_still_to_come():
    reply = read_message(coe(3, 0x41, 0x1008, 0, struct.pack("<I", 40) + b"eRob"))
    assert upload_value(reply) == (b"eRob", 40)


def test_an_upload_segment_is_matched_by_its_toggle_and_a_short_one_gives_its_used_bytes():
    expected = Expected(SCS_UPLOAD_SEGMENT, 0x1008, 0, toggle=0x10)
    short = read_message(mailbox_message(struct.pack("<HB", 0x3000, 0x10 | 4 << 1 | 1) + b"abc" + bytes(4), 3, 2))
    assert expected.answered_by(short) and segment_data(short) == (b"abc", True)
    other_toggle = read_message(mailbox_message(struct.pack("<HB", 0x3000, 0x00) + bytes(7), 3, 2))
    assert not expected.answered_by(other_toggle)


@given(low=st.integers(0, 0x1F), service=st.sampled_from([2, 3]))
def test_an_abort_for_the_object_is_taken_under_either_service_whatever_its_low_bits(low, service):
    reply = read_message(coe(service, 0x80 | low, 0x1C12, 0, struct.pack("<I", 0x06010002)))
    assert reply.kind == ABORT and reply.detail == 0x06010002 and DOWNLOAD.answered_by(reply)


def test_a_reply_for_another_object_or_of_another_kind_does_not_answer():
    assert not DOWNLOAD.answered_by(read_message(coe(3, 0x60, 0x1C12, 1)))
    assert not DOWNLOAD.answered_by(read_message(coe(3, 0x60, 0x1C13, 0)))
    assert not DOWNLOAD.answered_by(read_message(coe(3, 0x43, 0x1C12, 0)))  # an upload reply


def test_what_is_not_an_sdo_reply_is_named_by_the_byte_that_did_not_fit():
    assert read_message(coe(3, 0xA0, 0x1C12, 0)).describe() == "command byte 0xA0 under CoE service 3"
    assert read_message(coe(8, 0x02)).describe() == "CoE service 8 (header byte 0x80)"
    eoe = read_message(mailbox_message(bytes(10), 0x02, 1))
    assert eoe.kind == UNRECOGNISED and eoe.describe() == "mailbox type 0x2 (EoE), type byte 0x12"
    assert read_message(coe(2, 0x40, 0x6076, 0)).kind == UNRECOGNISED  # a request from the slave


def test_a_message_shorter_than_it_says_is_malformed():
    truncated = struct.pack("<HHBB", 200, 0, 0, 0x13) + bytes(20)
    assert read_message(truncated).kind == MALFORMED
    assert read_message(mailbox_message(struct.pack("<HB", 0x3000, 0x60), 3, 1)).kind == MALFORMED


def test_emergencies_and_mailbox_errors_are_told_apart():
    emergency = read_message(mailbox_message(struct.pack("<HHB5x", 0x1000, 0x8500, 0), 3, 1))
    assert (emergency.kind, emergency.detail) == (EMERGENCY, 0x8500)
    error = read_message(mailbox_message(struct.pack("<HH", 0x0001, 0x0002), 0x00, 1))
    assert (error.kind, error.detail) == (MAILBOX_ERROR, 2)
    assert read_message(coe(3, 0x60, 0x1C12, 0)).kind == SDO


def test_a_reply_is_late_only_when_it_answers_an_earlier_request():
    earlier = [Expected(SCS_UPLOAD, 0x6076, 0, sent_at=1.0), Expected(SCS_DOWNLOAD, 0x1C12, 0, sent_at=2.0)]
    late, answered = why_dropped(read_message(coe(3, 0x6F, 0x1C12, 0)), earlier)
    assert (late, answered) == (LATE, earlier[1])
    assert why_dropped(read_message(coe(3, 0x60, 0x1C13, 0)), earlier) == (OTHER_OBJECT, None)
    assert why_dropped(read_message(coe(3, 0xA0)), earlier) == (UNRECOGNISED, None)
    assert why_dropped(read_message(coe(3, 0x60, 0x1C12, 0)), []) == (OTHER_OBJECT, None)
