"""The DDS options' bad input: one line, non-zero, before anything starts."""

from __future__ import annotations

import subprocess
import sys

import pytest

from humanoid_prime.bench.dds import bench_dds

PRIME = [sys.executable, "-m", "humanoid_prime"]


@pytest.mark.parametrize(("args", "env", "says"), [
    (["sim", "--domain", "3"], {}, "prime sim: --domain needs --dds"),
    (["sim", "--dds-control"], {}, "prime sim: --dds-control needs --dds"),
    (["bringup", "--namespace", "left"], {}, "prime bringup: --namespace needs --dds"),
    (["sim", "--dds", "--namespace", "left/9arm"], {}, "--namespace 'left/9arm': '9arm' is not a ROS 2 name"),
    (["sim", "--dds"], {"ROS_AUTOMATIC_DISCOVERY_RANGE": "MOON"},
     "prime sim: ROS_AUTOMATIC_DISCOVERY_RANGE='MOON' is not one of SUBNET, LOCALHOST, OFF, SYSTEM_DEFAULT"),
    (["sim", "--dds", "--domain", "999"], {}, "--domain: must be in 0..232, got 999"),
    (["bringup", "--dds", "--domain", "-1"], {}, "--domain"),
    (["sim", "--dds"], {"ROS_DOMAIN_ID": "abc"}, "prime sim: ROS_DOMAIN_ID='abc' is not a domain id"),
    (["sim", "--dds"], {"ROS_DOMAIN_ID": "500"}, "prime sim: ROS_DOMAIN_ID 500 is outside the ROS 2 domain ids"),
    (["sim", "--ros-backend", "dds"], {}, "prime sim: --ros-backend needs --dds"),
    (["sim", "--dds", "--ros-backend", "rclpy"], {"PYTHONPATH": ""},  # Prime's own venv, no ROS 2 sourced
     "--ros-backend rclpy: rclpy cannot be imported here; source a ROS 2 install"),
    (["remote", "--wave", "left_knee"], {}, "prime remote: --wave: 'left_knee' is not a joint of Prime"),
    (["remote", "--pose", "dab"], {}, "prime remote: --pose: no pose 'dab'"),
    (["remote", "--amplitude", "nan"], {}, "--amplitude"),
])
def test_bad_dds_input_is_one_line(args, env, says, domain, monkeypatch):
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    done = subprocess.run([*PRIME, *args, "--duration", "1"], capture_output=True, text=True, timeout=120)
    assert done.returncode != 0
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and says in lines[0], done.stderr


def test_remote_without_a_prime_says_so(domain):
    done = subprocess.run([*PRIME, "remote", "--wait", "0.5", "--duration", "1"], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        f"prime remote: no joint states from Prime on ROS 2 domain {domain} within 0.5 s (is it running with --dds, "
        "in the same domain and namespace, reachable on this network?)"]


def test_the_dds_benchmark_measures_both_rates_with_a_subscriber(domain):
    results = bench_dds(seconds=0.5)
    for rate in ("50_hz", "1000_hz"):
        bridged = results[rate]["with"]
        assert bridged["bridge"]["topics"]["/prime/joint_states"]["published"] == bridged["ticks"]
        assert bridged["subscriber"]["received"] > 0
        assert results[rate]["without"]["ticks"] == bridged["ticks"]
        for paired in ("paired", "tap_paired"):  # attached and detached turns of one run, each with its median
            figures = results[rate][paired]["paired_us"]
            assert figures["added"] == pytest.approx(figures["attached"] - figures["detached"], abs=0.11)
        assert results[rate]["added_tick_us_median"] == results[rate]["paired"]["paired_us"]["added"]
