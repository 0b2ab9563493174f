"""``bench_sito``: the Sito benchmark reports the tick cost and the bus load DESIGN §6 measures."""

import pytest

from humanoid_prime.bench.sito import TARGET_LOAD_PERCENT, bench_sito

pytestmark = pytest.mark.realtime  # emulated wrists on the wall clock, measured


def test_bench_sito_reports_cost_and_load_at_50_hz():
    result = bench_sito(seconds=0.5)
    assert (result["motors"], result["update_rate"], result["ticks"]) == (4, 50.0, 25)
    assert 0 < result["read_write_us"]["median"] <= result["read_write_us"]["p99"]
    assert 0 < result["read_write_warm_us"]["median"] <= result["read_write_warm_us"]["p99"]
    assert result["flags"] == {}


def test_host_traffic_at_50_hz_is_one_command_per_motor_per_tick_plus_changed_gains():
    result = bench_sito(seconds=0.5)
    # 4 commands per tick at 50 Hz; gains unchanged after activation except the first tick and one refresh
    assert 200.0 <= result["host_frames_per_s"] <= 200.0 + 2 * 4 / 0.5
    assert result["host_load_percent"] < TARGET_LOAD_PERCENT == 5.0
    assert result["meets_target"]
