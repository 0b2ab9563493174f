"""Rate: fixed-rate pacing on an injected clock, one overrun policy."""

from __future__ import annotations

import pytest

from doubles.control import Clock
from humanoid_prime.control.rate import Rate
from humanoid_prime.errors import PrimeError


def test_the_first_wait_starts_the_schedule_without_waiting():
    clock = Clock(start=5.0)
    rate = Rate(50.0, clock=clock, sleep=clock.sleep)
    assert rate.wait() is True
    assert clock.now == 5.0
    assert rate.deadline == 5.0


def test_each_wait_returns_at_the_next_deadline_whatever_the_work_took():
    clock = Clock(start=0.0)
    rate = Rate(50.0, clock=clock, sleep=clock.sleep)
    ends = []
    for work_s in (0.0, 0.003, 0.015, 0.0):
        rate.wait()
        ends.append(round(clock.now, 9))
        clock.now += work_s
    assert ends == [0.0, 0.02, 0.04, 0.06]
    assert rate.overruns == 0


def test_an_iteration_past_the_next_deadline_is_one_overrun_and_the_schedule_restarts_from_then():
    clock = Clock(start=0.0)
    rate = Rate(50.0, clock=clock, sleep=clock.sleep)
    rate.wait()
    clock.now += 0.045  # overran two deadlines
    assert rate.wait() is False
    assert clock.now == pytest.approx(0.045)  # no wait, no burst
    assert rate.overruns == 1
    rate.wait()
    assert clock.now == pytest.approx(0.065)  # one period after the restart


def test_the_last_part_of_a_period_is_spun_not_slept():
    clock = Clock(start=0.0, step=1e-5)
    slept = []

    def sleep(seconds: float) -> None:
        slept.append(seconds)
        clock.now += seconds

    rate = Rate(100.0, clock=clock, sleep=sleep, spin_s=0.002)
    rate.wait()
    rate.wait()
    assert slept and slept[0] == pytest.approx(0.008, abs=1e-4)
    assert clock.now >= rate.deadline == pytest.approx(0.01, abs=1e-4)


def test_a_sleep_that_reports_an_event_ends_the_wait_at_once():
    clock = Clock(start=0.0)
    rate = Rate(10.0, clock=clock, sleep=lambda seconds: True)
    rate.wait()
    assert rate.wait() is True
    assert clock.now == 0.0


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), True])
def test_a_rate_that_is_not_a_positive_number_is_refused(bad):
    with pytest.raises(PrimeError, match="positive number of Hz"):
        Rate(bad)
