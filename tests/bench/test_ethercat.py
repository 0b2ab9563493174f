"""``bench_ethercat``: the EtherCAT benchmark on the emulated ring, put together through ``assemble`` as every run
is, brings the ten drives up and measures the cycle and the gain switches without a flag or a lost frame."""

import pytest

from humanoid_prime.bench.ethercat import bench_ethercat
from humanoid_prime.virtual.netns import netns_unavailable_reason

_REASON = netns_unavailable_reason()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(_REASON is not None, reason=_REASON or "")]


def test_bench_ethercat_brings_the_ring_up_and_measures_the_cycle_and_the_gain_switches():
    result = bench_ethercat(bringup_rates_hz=(1000.0,), cycles=20, switches=2)
    bringup = result["bringup"]["1000_hz"]
    assert result["slaves"] == 10 and bringup["bringup_cycles"] > 0
    assert 0.0 < bringup["op_seconds"] <= bringup["seconds"]  # OP within the manager's staged start
    assert result["cycle_us_back_to_back"]["n"] == 20 - 5  # the first five are the warm-up
    for switch in (result["sdo_switch_parallel"], result["sdo_switch_sequential"]):
        assert switch["switches"] == 2 and switch["writes_per_switch"] == 2 * 10 and switch["wall_ms"]["n"] == 2
    assert result["wkc_errors"] == 0 and result["flags_at_end"] == {}
