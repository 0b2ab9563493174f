"""Our own register frames: a reply is taken only for the request it answers, a late one never for a later
request, and an index whose reply is still out is not used again until it came."""

from __future__ import annotations

import struct

import pytest

from doubles.link import EmulatedClock, RingHub
from doubles.wire import STATION_BASE, WireMaster
from humanoid_prime.drivers.ethercat.link import (
    FIRST_INDEX,
    Channel,
    brd,
    build_frame,
    fprd,
    fpwr,
    index_filter,
    index_ranges,
    parse_reply,
)
from humanoid_prime.virtual.ring.options import RingOptions
from humanoid_prime.virtual.ring.ring import Ring

AL_STATUS = 0x0130


def make(slaves: int = 2) -> tuple[Ring, RingHub, EmulatedClock]:
    clock = EmulatedClock()
    ring = Ring(RingOptions(slaves=slaves), clock=lambda: round(clock.now * 1e9))
    WireMaster(ring, round(clock.now * 1e9)).set_station_addresses()
    return ring, RingHub(ring, clock), clock


def channel(hub: RingHub, clock: EmulatedClock, indices=(FIRST_INDEX, FIRST_INDEX + 1)) -> Channel:
    return Channel(hub.port(indices), indices, clock=clock)


def al_state(reply) -> int:
    return struct.unpack("<H", reply[0].data)[0] & 0x0F


def test_a_reply_comes_back_with_its_data_and_working_counter():
    _ring, hub, clock = make(3)
    replies = channel(hub, clock).exchange([brd(0x0000, 1), fprd(STATION_BASE + 1, AL_STATUS, 2)], timeout_s=0.01)
    assert [r.wkc for r in replies] == [3, 1]
    assert al_state(replies[1:]) == 0x01  # INIT


def test_a_late_reply_is_never_taken_for_a_later_request_its_index_waits_until_it_came():
    ring, hub, clock = make()
    link = channel(hub, clock)  # two indices: without the wait, the third exchange would reuse the first's
    read = fprd(STATION_BASE, AL_STATUS, 2)
    hub.hold_next(0.030)
    assert link.exchange([read], timeout_s=0.010, repeat=False) is None  # INIT, 30 ms late
    setup = WireMaster(ring, round(clock.now * 1e9))
    setup.program_mailbox(STATION_BASE)
    setup.request_state(STATION_BASE, 0x02)  # the slave goes on to PRE-OP
    assert al_state(link.exchange([read], timeout_s=0.010, repeat=False)) == 0x02
    hub.hold_next(0.030)  # the late INIT comes back while the next read waits for its own reply
    assert al_state(link.exchange([read], timeout_s=0.050, repeat=False)) == 0x02  # not the late INIT
    assert link.late_count == 1 and link.late[0].late_s == pytest.approx(0.030)


def test_a_frame_not_back_within_the_retry_time_is_sent_again_and_the_first_copy_s_late_reply_is_counted():
    _ring, hub, clock = make()
    link = channel(hub, clock, indices=tuple(range(FIRST_INDEX, FIRST_INDEX + 4)))
    hub.hold_next(0.005)
    replies = link.exchange([fprd(STATION_BASE, AL_STATUS, 2)], timeout_s=0.050)
    assert replies[0].wkc == 1 and link.resent == 1
    clock.sleep(0.010)  # meanwhile the first copy came back; the next exchange reads it first
    link.exchange([fprd(STATION_BASE, AL_STATUS, 2)], timeout_s=0.050)
    assert link.late_count == 1


def test_a_reply_whose_datagrams_are_not_the_requests_is_not_taken():
    frame = build_frame(0x50, [fprd(STATION_BASE, AL_STATUS, 2)])
    assert parse_reply(frame, [fprd(STATION_BASE, AL_STATUS, 2)])[0] == 0x50
    assert parse_reply(frame, [fprd(STATION_BASE + 1, AL_STATUS, 2)]) is None  # another slave
    assert parse_reply(frame, [fprd(STATION_BASE, 0x080D, 2)]) is None  # another register
    assert parse_reply(frame, [fprd(STATION_BASE, AL_STATUS, 6)]) is None  # another length
    assert parse_reply(frame, [fpwr(STATION_BASE, AL_STATUS, b"\x00\x00")]) is None  # another command


def test_a_lost_frame_gives_none_after_the_timeout_and_the_channel_goes_on():
    _ring, hub, clock = make()
    link = channel(hub, clock, indices=tuple(range(FIRST_INDEX, FIRST_INDEX + 4)))
    hub.lose_next()
    hub.lose_next()
    assert link.exchange([fprd(STATION_BASE, AL_STATUS, 2)], timeout_s=0.003) is None
    assert link.unanswered == 1
    assert link.exchange([fprd(STATION_BASE, AL_STATUS, 2)], timeout_s=0.003)[0].wkc == 1


def test_the_indices_are_split_between_channels_above_soems_and_the_filter_passes_only_a_channel_s():
    ranges = index_ranges(11)
    assert ranges[0].start == FIRST_INDEX >= 16 and ranges[-1].stop <= 0x100
    assert all(len(r) >= 2 for r in ranges) and len({i for r in ranges for i in r}) == sum(len(r) for r in ranges)
    program = index_filter(0x50, 0x5F)
    assert len(program) == 7 * 8 and struct.unpack_from("<I", program, 3 * 8 + 4)[0] == 0x50
