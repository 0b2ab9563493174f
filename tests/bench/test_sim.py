"""``bench_sim``: the simulation-speed benchmark reports what DESIGN §6 measures."""

import pytest

from humanoid_prime.bench.sim import bench_sim
from humanoid_prime.modes import Mode

pytestmark = pytest.mark.realtime  # the benchmark's figures are wall-clock measurements


def test_bench_sim_runs_every_mode_for_the_requested_simulated_time():
    result = bench_sim(seconds=2.0)
    assert result["sim_seconds"] == 2.0
    assert result["ticks"] == 100  # the robot's 50 Hz control (DESIGN §6), not the simulation file's 200 Hz
    assert set(result["modes_visited"]) == set(Mode)
    assert result["fallbacks"] == 0


def test_bench_sim_judges_its_speed_as_a_share_of_mujocos_own_in_the_run_at_the_robots_rates():
    result = bench_sim(seconds=0.5)
    assert result["realtime_factor"] == pytest.approx(result["sim_seconds"] / result["wall_seconds"], rel=1e-3)
    fraction = result["realtime_factor"] / result["floors"]["realtime_factor"]
    assert result["meets_target"] == (fraction >= 0.9)  # DESIGN §6
    assert 0 < result["tick_us"]["median"] <= result["tick_us"]["p99"]
    assert (result["update_rate"], result["physics_rate"]) == (50.0, 1000.0)


def test_bench_sim_shows_mujocos_own_steps_in_the_run_as_the_floor_and_splits_the_tick():
    result = bench_sim(seconds=0.2)
    floors = result["floors"]
    assert floors["realtime_factor"] == pytest.approx(1e6 / (floors["mj_step_us"] * 1000.0), rel=0.01)
    assert result["floor_fraction"] == pytest.approx(result["realtime_factor"] / floors["realtime_factor"], rel=0.01)
    assert 0 < result["floor_fraction"] < 1  # the physics is part of the run's wall time
    assert 0 < result["tick_cpu_us"]["median"] < result["tick_us"]["median"]
