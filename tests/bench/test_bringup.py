"""``bringup_figures``: what the bring-up benchmark makes of an emulated run's summary (the run itself is the
emulated bring-up the CLI tests drive end to end)."""

import pytest

from humanoid_prime.bench.bringup import bringup_figures
from humanoid_prime.virtual.harness import EMULATOR_STAGE


def summary(**changes):
    ticks = {"median": 90.0, "p99": 200.0, "max": 400.0}
    base = {
        "bringup_seconds": 1.7,
        "stages": [{"name": "configuration", "seconds": 0.06}, {"name": EMULATOR_STAGE, "seconds": 0.52},
                   {"name": "hardware activate", "seconds": 0.99}, {"name": "first tick", "seconds": 0.001}],
        "ethercat_bringup": {"seconds": 0.99, "cycles": 450}, "ok": True, "problems": [],
        "end": {"slaves": 10, "sito": 4}, "update_rate": 50.0,
        "mode_switches": [{"mode": "DAMPING", "wall_seconds": 0.012, "skew_seconds": 0.004},
                          {"mode": "STANDBY", "wall_seconds": 0.018, "skew_seconds": 0.006},
                          {"mode": "ZERO_TORQUE", "wall_seconds": 0.5, "skew_seconds": 0.4}],
        "tick_us": ticks, "tick_cpu_us": ticks, "tick_io_us": ticks, "jitter_us": {"p99": 8.0},
        "ticks": 700, "overruns": 0, "faults": [],
    }
    base.update(changes)
    return base


def test_the_bringup_figure_is_the_stacks_and_the_emulated_robots_own_start_is_reported_beside_it():
    figures = bringup_figures(summary())
    assert figures["emulator_start_seconds"] == 0.52
    assert figures["bringup_seconds"] == pytest.approx(1.7 - 0.52)


def test_a_run_on_the_robot_has_no_emulator_stage_to_take_out():
    figures = bringup_figures(summary(stages=[{"name": "configuration", "seconds": 0.06}]))
    assert (figures["bringup_seconds"], figures["emulator_start_seconds"]) == (1.7, 0)


def test_switch_figures_count_the_damping_and_standby_switches_only():
    figures = bringup_figures(summary())
    assert figures["switches"] == 2
    assert figures["switch_seconds"] == {"median": pytest.approx(0.015), "max": 0.018}
    assert figures["skew_seconds"]["max"] == 0.006
