"""The wake-up latency probe's verdict against the periods the robot runs at (given wake-ups, not measured ones:
a timed unit test would judge the machine, not the code)."""

from __future__ import annotations

from humanoid_prime.doctor.latency import Wakeups, latency_check
from humanoid_prime.doctor.report import Verdict

UPDATE_RATE = (0.02, "update_rate 50 Hz, prime_controllers.yaml")
KHZ = (0.001, "--rate 1000 Hz")


def wakeups(*lateness_ms: float) -> Wakeups:
    return Wakeups(tuple(ms / 1e3 for ms in lateness_ms), 0.001, "SCHED_FIFO 80")


def test_wake_ups_well_within_the_period_pass_and_say_what_share_they_took():
    check = latency_check(wakeups(*[0.05] * 99, 0.4), [UPDATE_RATE])
    assert check.verdict is Verdict.PASS
    assert check.found == ("worst wake-up 0.40 ms late, p99 0.05 ms, of 100 at 1000 Hz (SCHED_FIFO 80); 2% of the "
                           "20 ms period (update_rate 50 Hz, prime_controllers.yaml)")


def test_a_wake_up_a_whole_period_late_fails_against_that_period_only():
    check = latency_check(wakeups(*[0.05] * 99, 1.5), [UPDATE_RATE, KHZ])
    assert check.verdict is Verdict.FAIL
    assert "150% of the 1 ms period (--rate 1000 Hz): the loop would miss ticks" in check.found
    assert "8% of the 20 ms period" in check.found
    assert "PREEMPT_RT" in check.fix


def test_a_quarter_period_worst_case_or_a_tenth_period_p99_warns():
    assert latency_check(wakeups(*[0.05] * 99, 6.0), [UPDATE_RATE]).verdict is Verdict.WARN
    assert latency_check(wakeups(*[2.5] * 100), [UPDATE_RATE]).verdict is Verdict.WARN
    assert latency_check(wakeups(*[1.5] * 100), [UPDATE_RATE]).verdict is Verdict.PASS
