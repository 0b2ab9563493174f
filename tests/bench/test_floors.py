"""The physical floors shown beside the benchmark figures, against the numbers worked out by hand."""

import pytest

from humanoid_prime.bench.floors import can_frame_s, ethercat_cycle_s


def test_one_ethercat_cycle_of_ten_erob_is_its_372_byte_frame_plus_ten_slave_delays():
    # 2 EtherCAT header + 12 LRW overhead + 10 * (14 out + 16 in) + 20 FRMW = 334 bytes, + 38 of Ethernet framing
    assert ethercat_cycle_s(10, 14, 16) == pytest.approx(372 * 8 / 100e6 + 10 * 0.7e-6)


def test_a_tiny_ethercat_frame_is_padded_to_the_ethernet_minimum():
    assert ethercat_cycle_s(1, 1, 1, bit_rate=100e6) == pytest.approx((46 + 38) * 8 / 100e6 + 0.7e-6)


def test_an_extended_can_frame_with_8_bytes_is_131_bits_and_160_with_worst_stuffing():
    assert can_frame_s() == pytest.approx(131e-6)
    assert can_frame_s(worst_stuffing=True) == pytest.approx(160e-6)
    assert can_frame_s(0, bit_rate=500e3) == pytest.approx(67 / 500e3)
