"""``bench_doctor``: prime doctor on the healthy virtual Prime, its start-up plus checks beside what no faster code
could take less than."""

import pytest

from humanoid_prime.bench.doctor import bench_doctor
from humanoid_prime.virtual.netns import netns_unavailable_reason

REASON = netns_unavailable_reason()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(REASON is not None, reason=f"no virtual Prime: {REASON}")]


def test_bench_doctor_times_start_up_plus_checks_apart_from_the_emulator_s_start_beside_its_floor():
    result = bench_doctor(runs=1)
    (run,) = result["seconds"]["runs"]
    assert result["floors"]["seconds"] < run == result["seconds"]["median"]
    assert run == pytest.approx(result["wall_seconds"][0] - result["emulator_start_seconds"][0], abs=1e-3)
    assert result["checks_seconds"][0] < run
    assert result["verdicts"]["passed"] > 0
