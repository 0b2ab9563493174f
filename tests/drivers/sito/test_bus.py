"""The CAN transport helpers: frame length on the wire, failure classification, opening a bus."""

from __future__ import annotations

import errno
import gc
import math

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from humanoid_prime.drivers.sito.bus import (
    BUS_BUDGET,
    FRAMES_PER_WRIST,
    bus_cycle,
    can_frame_bits,
    crc15,
    frame_bits,
    is_interface_down,
    is_queue_full,
    open_bus,
    stuff_bit_count,
    to_bits,
)
from humanoid_prime.errors import PrimeError


def test_five_equal_bits_take_one_stuff_bit():
    assert stuff_bit_count([0, 0, 0, 0, 0]) == 1


def test_a_stuff_bit_starts_the_next_run():
    # 0 x5, stuff 1, then 1 x4 makes five ones: a second stuff bit.
    assert stuff_bit_count([0] * 5 + [1] * 4) == 2


def test_alternating_bits_need_no_stuffing():
    assert stuff_bit_count([0, 1] * 40) == 0


def test_crc15_residue_of_a_frame_with_its_crc_is_zero():
    bits = to_bits(0x05061609, 29) + to_bits(0x0064145F000028BE, 64)
    assert crc15(bits + to_bits(crc15(bits), 15)) == 0


def test_empty_standard_frame_with_id_0_is_53_bits():
    # 34 dominant bits from SOF to CRC take 6 stuff bits; 13 bits of delimiters, ACK, EOF, intermission.
    assert frame_bits(can.Message(arbitration_id=0, is_extended_id=False, data=b"")) == 53


@given(st.integers(0, 0x1FFFFFFF), st.binary(min_size=8, max_size=8))
def test_extended_8_byte_frame_is_131_to_160_bits(ident, data):
    assert 131 <= frame_bits(can.Message(arbitration_id=ident, is_extended_id=True, data=data)) <= 160


def test_the_worst_case_frame_length_bounds_every_exact_one():
    assert (can_frame_bits(), can_frame_bits(worst_stuffing=True)) == (131, 160)


def test_the_bus_cycle_is_the_control_period_while_the_wrists_frames_fit_it():
    assert bus_cycle(50.0, 4, 1e6) == (1, 20)
    assert bus_cycle(250.0, 4, 1e6) == (1, 4)
    assert bus_cycle(1000.0, 4, 1e6) == (4, 4)  # 12 frames need 1.6-1.9 ms: every 4th tick
    assert bus_cycle(2.0, 4, 1e6) == (1, 254)  # the slowest feedback the firmware takes
    assert bus_cycle(1000.0, 4, 500e3) == (7, 7)


@pytest.mark.parametrize("rate", [10.0, 50.0, 100.0, 300.0, 320.0, 400.0, 500.0, 999.0, 1000.0, 1500.0, 2000.0])
@pytest.mark.parametrize("wrists", [1, 4, 8])
def test_the_bus_cycle_is_the_fewest_ticks_whose_time_holds_the_frames_within_the_budget(rate, wrists):
    every, feedback_ms = bus_cycle(rate, wrists, 1e6)
    bits = wrists * FRAMES_PER_WRIST * can_frame_bits(worst_stuffing=True)
    assert bits / (every / rate) <= BUS_BUDGET * 1e6 * (1 + 1e-9)
    assert every == 1 or bits / ((every - 1) / rate) > BUS_BUDGET * 1e6
    assert 1 <= feedback_ms <= 254 and (feedback_ms == 254 or feedback_ms / 1000 >= every / rate - 1e-12)


def test_a_control_rate_that_is_no_rate_is_refused():
    for rate in (0.0, -50.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="positive number of Hz"):
            bus_cycle(rate, 4, 1e6)


def test_enobufs_is_a_full_queue_not_a_dead_interface():
    exc = can.CanOperationError("Failed to transmit: No buffer space available", errno.ENOBUFS)
    assert is_queue_full(exc)
    assert not is_interface_down(exc)


def test_enetdown_is_a_dead_interface():
    exc = can.CanOperationError("Failed to transmit: Network is down", errno.ENETDOWN)
    assert is_interface_down(exc)
    assert not is_queue_full(exc)


def test_a_closed_bus_is_a_dead_interface():
    assert is_interface_down(can.CanOperationError("Cannot operate on a closed bus"))


def test_opening_a_missing_socketcan_channel_says_how_to_bring_it_up(robot):
    with pytest.raises(PrimeError, match="ip link set can_missing0 up type can bitrate 1000000"):
        open_bus(robot.hardware, channel="can_missing0")


def test_open_bus_takes_interface_and_channel_overrides(robot):
    bus = open_bus(robot.hardware, interface="virtual", channel="sito-open-bus-test")
    try:
        assert bus.channel_info == "Virtual bus channel sito-open-bus-test"
    finally:
        bus.shutdown()


def test_a_bus_whose_constructor_fails_is_shut_down_not_left_to_its_finaliser(robot, caplog):
    # udp_multicast opens its socket after python-can's base counted the bus open; an unknown group fails there
    with pytest.raises(PrimeError, match="cannot open CAN channel 'notanip' \\(udp_multicast\\)"):
        open_bus(robot.hardware, interface="udp_multicast", channel="notanip")
    gc.collect()
    assert "not properly shut down" not in caplog.text
