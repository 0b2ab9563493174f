"""The CAN transport helpers: frame length on the wire, failure classification, opening a bus."""

from __future__ import annotations

import errno

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from humanoid_prime.drivers.sito.bus import (
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
