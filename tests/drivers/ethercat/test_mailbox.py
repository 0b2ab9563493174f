"""Our CoE mailbox against the emulated eRob: SDO transfers whose late, repeated or lost replies are never taken
as the answer to another request, and that never write a SyncManager register."""

from __future__ import annotations

import struct
import threading

import pytest

from doubles.link import EmulatedClock, RingHub
from doubles.wire import MAILBOX_IN, MAILBOX_OUT, STATION_BASE, WireMaster
from humanoid_prime.drivers.erob.objects import RATED_TORQUE, TXPDO_MAP
from humanoid_prime.drivers.ethercat.errors import SdoError, SdoTimeout
from humanoid_prime.drivers.ethercat.link import FIRST_INDEX, Channel
from humanoid_prime.drivers.ethercat.mailbox import REQUEST_ATTEMPTS, CoeMailbox, MailboxLayout
from humanoid_prime.drivers.ethercat.wire import mailbox_message
from humanoid_prime.virtual.ring.options import RingOptions
from humanoid_prime.virtual.ring.ring import Ring

IDENTITY_VENDOR = (0x1018, 1)
MS = 0.001


def make(**options) -> tuple[Ring, RingHub, CoeMailbox]:
    clock = EmulatedClock()
    ring = Ring(RingOptions(slaves=1, **options), clock=lambda: round(clock.now * 1e9))
    setup = WireMaster(ring, round(clock.now * 1e9))
    setup.set_station_addresses()
    size = ring.options.mailbox_size
    setup.program_mailbox(STATION_BASE, size)
    setup.request_state(STATION_BASE, 0x02)
    hub = RingHub(ring, clock)
    indices = tuple(range(FIRST_INDEX, FIRST_INDEX + 8))
    mailbox = CoeMailbox(Channel(hub.port(indices), indices, clock=clock), 0, STATION_BASE,
                         MailboxLayout(MAILBOX_OUT, size, MAILBOX_IN if size <= 0x80 else MAILBOX_OUT + size, size),
                         clock=clock, sleep=clock.sleep)
    return ring, hub, mailbox


def sync_manager_writes(hub: RingHub) -> list[bytes]:
    """Frames we sent that write anything in 0x0800-0x08FF (the SyncManagers)."""
    out = []
    for frame in hub.sent:
        offset = 16
        while offset + 10 <= len(frame):
            command, _index, _adp, ado, length = struct.unpack_from("<BBHHH", frame, offset)
            if command in (2, 5, 8) and 0x0800 <= ado < 0x0900:
                out.append(frame)
            offset += 10 + (length & 0x7FF) + 2
            if not length & 0x8000:
                break
    return out


def test_an_upload_returns_the_drive_s_value_and_a_download_changes_it():
    ring, _hub, mailbox = make()
    assert mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.1) == struct.pack("<I", 0x5A65726F)
    mailbox.download(0x2383, 0, b"\x01\x00\x00\x00", timeout_s=0.1)
    assert ring.slaves[0].drive.gate.value == 1


def test_a_long_value_comes_in_segments():
    _ring, _hub, mailbox = make(mailbox_size=32)
    assert mailbox.upload(0x1008, 0, timeout_s=0.1) == b"eRob rotary actuator, CiA402 (emulated)"


def test_an_abort_names_its_code():
    _ring, _hub, mailbox = make()
    with pytest.raises(SdoError) as error:
        mailbox.download(RATED_TORQUE, 0, b"\x00\x00\x00\x00", timeout_s=0.1)
    assert error.value.abort_code == 0x06010002
    assert "attempt to write a read only object" in str(error.value)


def test_a_reply_that_came_after_its_request_was_given_up_on_is_not_the_answer_to_the_next():
    ring, hub, mailbox = make(mailbox_latency_s=0.0005)
    ring.latency.script(1, 0.030)  # the rated torque's reply: 30 ms late, past a 10 ms timeout
    with pytest.raises(SdoError, match="no reply within 10 ms"):
        mailbox.upload(RATED_TORQUE, 0, timeout_s=0.010)
    hub.clock.sleep(0.030)  # the late reply waits in the read mailbox now
    assert mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.1) == struct.pack("<I", 0x5A65726F)
    (dropped,) = mailbox.log.records
    assert dropped.reason == "late" and "an upload reply for 0x6076:00" in dropped.what
    assert 0.030 <= dropped.late_s <= 0.045  # from the request it answers
    assert mailbox.log.given_up == 1  # the one request given up on: a ring's late drops are at most its count


def test_a_late_write_reply_is_not_read_as_an_empty_value_of_the_same_object():
    # SOEM's read-back of the PDO mapping took such a reply for a 0-byte answer and counted the entry as 0 bits
    ring, _hub, mailbox = make(mailbox_latency_s=0.0005)
    ring.latency.script(1, 0.030)
    with pytest.raises(SdoError):
        mailbox.download(TXPDO_MAP, 0, b"\x00", timeout_s=0.010)
    assert mailbox.upload(TXPDO_MAP, 0, timeout_s=0.1) == b"\x00"  # the value, not the late "written"
    assert mailbox.upload(TXPDO_MAP, 1, timeout_s=0.1) == struct.pack("<I", 0x60640020)
    assert mailbox.log.records[0].reason == "late" and "a download reply for 0x1A00:00" in mailbox.log.records[0].what


def test_a_reply_read_out_but_lost_on_its_way_back_is_asked_for_again_never_by_a_syncmanager_write():
    ring, hub, mailbox = make()
    hub.lose_next(lambda frame, took_reply: took_reply)
    assert mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.2) == struct.pack("<I", 0x5A65726F)
    assert mailbox.requests_again == 1
    assert sync_manager_writes(hub) == []
    assert ring.slaves[0].esc.al_status == 0x02  # still in PRE-OP, its mailbox on


def test_a_request_whose_every_reply_is_lost_is_asked_again_and_each_copy_given_up_once():
    _ring, hub, mailbox = make()
    for _ in range(REQUEST_ATTEMPTS):
        hub.lose_next(lambda frame, took_reply: took_reply)
    with pytest.raises(SdoTimeout):
        mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.5)
    assert (mailbox.requests_again, mailbox.log.given_up) == (REQUEST_ATTEMPTS - 1, REQUEST_ATTEMPTS)


def test_a_request_whose_frame_was_lost_before_the_slave_is_sent_again_and_served_once():
    ring, hub, mailbox = make()
    mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.1)  # (the first request carries counter 0, which nobody checks)
    hub.lose_next()  # the frame with the request: the slave got it, its reply frame is lost
    mailbox.download(0x2383, 0, b"\x01\x00\x00\x00", timeout_s=0.2)
    assert [entry[2:5] for entry in ring.sdo_log] == [(0x2383, 0, 1)]  # once, although sent twice
    assert sum(1 for frame in hub.sent if len(frame) > 100 and frame[16] in (4, 5)) >= 3


def test_a_reply_held_back_by_a_slow_host_is_waited_for_within_the_timeout():
    _ring, hub, mailbox = make()
    hub.hold_next(0.020, lambda frame, took_reply: took_reply)
    assert mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.1) == struct.pack("<I", 0x5A65726F)
    assert mailbox.requests_again == 0


def test_a_reply_that_never_comes_is_told_from_a_host_too_slow_to_look_for_it():
    ring, hub, mailbox = make(mailbox_latency_s=0.0005)
    ring.latency.script(2, 1.0)
    with pytest.raises(SdoTimeout) as error:
        mailbox.upload(RATED_TORQUE, 0, timeout_s=0.1)
    assert error.value.delivered and error.value.looks > 10 and not error.value.host_slow
    assert error.value.verdict == "the drive did not answer"
    mailbox.sleep = lambda _s: hub.clock.sleep(0.040)  # every pause between two looks lasts 40 ms: a loaded host
    with pytest.raises(SdoTimeout) as error:
        mailbox.upload(RATED_TORQUE, 0, timeout_s=0.1)
    assert error.value.host_slow and error.value.verdict == "this host did not look in time"
    assert "this process went 40 ms without a look (a loaded host)" in error.value.problem


def request_counters(hub: RingHub) -> list[int]:
    """The mailbox counter of every request we wrote (the FPWR after the flush in each request frame)."""
    return [frame[16 + 10 + 128 + 2 + 10 + 5] >> 4 for frame in hub.sent
            if len(frame) > 200 and frame[16 + 10 + 128 + 2] == 0x05]


def test_requests_count_from_0_after_a_reset_then_1_to_7_and_round_again():
    _ring, hub, mailbox = make()
    for _ in range(9):
        mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.1)
    mailbox.reset_counter()  # another master used the mailbox (or is about to)
    mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.1)
    assert request_counters(hub) == [0, 1, 2, 3, 4, 5, 6, 7, 1, 0]


def test_replies_that_repeat_the_last_reply_s_counter_are_each_taken():
    # the slave's counter is its own sequence (ETG.1000.4): two replies in a row with one counter are two replies
    _ring, _hub, mailbox = make(quirks="counter")
    values = [mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.1) for _ in range(4)]
    assert values == [struct.pack("<I", 0x5A65726F)] * 4
    assert mailbox.log.snapshot() == {"late": 0, "other object": 0, "unrecognised": 0, "malformed": 0}


def test_a_slave_that_repeats_the_counter_of_the_last_request_does_not_serve_it_again():
    # why the counters matter: a request sent again after a lost frame is served once
    ring, _hub, _mailbox = make()
    setup = WireMaster(ring, 0)
    message = mailbox_message(struct.pack("<HBHBI", 0x2000, 0x23, 0x2383, 0, 1), 3, 5).ljust(128, b"\0")
    for _ in range(2):
        setup.fpwr(STATION_BASE, MAILBOX_OUT, message)
        setup.fprd(STATION_BASE, MAILBOX_IN, 128)
    assert len(ring.sdo_log) == 1


def test_an_emergency_in_the_mailbox_is_handed_on_and_the_transfer_goes_on():
    ring, _hub, mailbox = make(mailbox_latency_s=0.002)
    seen = []
    mailbox.on_emergency = lambda position, code: seen.append((position, code))
    ring.slaves[0].esc.post_mailbox(mailbox_message(struct.pack("<HHBBHH", 0x1000, 0x8500, 0, 0, 0, 0), 3, 4))
    assert mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.1) == struct.pack("<I", 0x5A65726F)
    assert seen == [(0, 0x8500)]


def test_two_threads_never_share_one_slave_s_mailbox():
    ring, hub, mailbox = make()
    inside = threading.Event()
    release = threading.Event()
    wire = mailbox.channel.wire
    original = wire.send
    sent_while_held = []

    def send(frame: bytes) -> None:
        if inside.is_set() and not release.is_set():
            sent_while_held.append(frame)
        original(frame)
        if not inside.is_set():
            inside.set()
            release.wait(5)

    wire.send = send
    got = {}
    first = threading.Thread(target=lambda: got.update(first=mailbox.upload(*IDENTITY_VENDOR, timeout_s=0.1)))
    first.start()
    assert inside.wait(5)
    second = threading.Thread(target=lambda: got.update(second=mailbox.upload(RATED_TORQUE, 0, timeout_s=0.1)))
    second.start()
    second.join(0.2)
    assert second.is_alive() and sent_while_held == []  # waiting for the first, not on the wire
    release.set()
    first.join(5)
    second.join(5)
    assert got == {"first": struct.pack("<I", 0x5A65726F), "second": struct.pack("<I", 23000)}
