"""SYNC0 is one number derived from the loop period; a different one is refused up front with the reason."""

from __future__ import annotations

import pytest

from doubles.master import FakeMaster
from humanoid_prime.drivers.ethercat.master import sync0_period_ns
from humanoid_prime.errors import PrimeError


def test_sync0_is_the_loop_period_at_50_hz():
    assert sync0_period_ns(50.0) == 20_000_000


def test_sync0_is_the_loop_period_at_1_khz():
    assert sync0_period_ns(1000.0) == 1_000_000


def test_an_override_equal_to_the_loop_period_is_accepted():
    assert sync0_period_ns(50.0, sync0_period_s=0.02) == 20_000_000


def test_a_sync0_faster_than_the_loop_is_refused_with_the_reason():
    with pytest.raises(PrimeError) as err:
        sync0_period_ns(50.0, sync0_period_s=0.001)
    text = str(err.value)
    assert "sync0_period 1 ms differs from the loop period 20 ms" in text
    assert "never locks" in text and "4616" in text


def test_a_cycle_below_the_erob_minimum_of_500_us_is_refused():
    with pytest.raises(PrimeError, match="below the eRob minimum of 500 us"):
        sync0_period_ns(4000.0)


def test_the_master_refuses_a_mismatched_sync0_when_constructed():
    with pytest.raises(PrimeError, match="4616"):
        FakeMaster(update_rate=50.0, sync0_period_s=0.001)


def test_the_master_derives_sync0_from_the_update_rate():
    assert FakeMaster(update_rate=50.0).sync0_ns == 20_000_000
