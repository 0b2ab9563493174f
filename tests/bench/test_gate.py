"""The gate's benchmark: the same 50 Hz tick with and without the body check, in one run, and while it refuses."""

from humanoid_prime.bench import TARGET_GATE_ADDED_TICK_US
from humanoid_prime.bench.gate import bench_gate


def test_bench_gate_reports_the_body_checks_cost_beside_the_tick_without_it_and_while_it_refuses():
    result = bench_gate(seconds=2.0)
    with_check, without = result["tick_cpu_us"]["with_body_check"], result["tick_cpu_us"]["without"]
    assert with_check["median"] > 0 and without["median"] > 0
    assert result["added_tick_us_median"] == round(with_check["median"] - without["median"], 1)
    assert result["floors"]["tick_cpu_us_median"] == without["median"]
    assert result["target_added_tick_us"] == TARGET_GATE_ADDED_TICK_US
    assert result["refusing"]["refused"] > 0  # the pushed arm was held every tick of its turns
