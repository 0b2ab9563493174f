"""Real-time measures of the control thread: each taken where allowed, each refusal said, the GC between ticks."""

import gc
import json
import os
import subprocess
import sys

import pytest

from humanoid_prime.runtime import realtime
from humanoid_prime.runtime.realtime import GcBetweenTicks, check_cpu, enter_realtime, leave_realtime


@pytest.fixture
def restored():
    interval, enabled = sys.getswitchinterval(), gc.isenabled()
    yield
    sys.setswitchinterval(interval)
    gc.unfreeze()
    (gc.enable if enabled else gc.disable)()


def refuse_scheduling(*_args):
    raise PermissionError(1, "Operation not permitted")


def test_a_refused_real_time_scheduler_is_said_and_the_rest_still_applies(monkeypatch, restored):
    monkeypatch.setattr(realtime.os, "sched_setscheduler", refuse_scheduling)
    report = enter_realtime(0.001, memory_refused="memory not locked (Cannot allocate memory: ...)")
    try:
        assert report.scheduling == "SCHED_OTHER" and not report.memory_locked
        assert report.refused == ["real-time scheduling refused (run as root or grant CAP_SYS_NICE)",
                                  "memory not locked (Cannot allocate memory: ...)"]
        assert "NOT real time: real-time scheduling refused" in report.line()
        assert report.switch_interval_s == pytest.approx(0.0001)
        assert sys.getswitchinterval() == pytest.approx(0.0001)
        assert not gc.isenabled() and report.gc_frozen > 0 and gc.get_freeze_count() > 0
    finally:
        leave_realtime(report)
    assert gc.isenabled() and gc.get_freeze_count() == 0
    assert sys.getswitchinterval() == pytest.approx(report.previous_switch_interval_s)


def test_the_switch_interval_is_never_raised_above_the_interpreters_default(monkeypatch, restored):
    monkeypatch.setattr(realtime.os, "sched_setscheduler", refuse_scheduling)
    report = enter_realtime(1.0, memory_refused=None)  # a tenth of 1 s would be 100 ms
    leave_realtime(report)
    assert report.switch_interval_s == pytest.approx(0.005)


def test_a_cpu_this_process_may_not_use_is_refused_by_number():
    allowed = sorted(os.sched_getaffinity(0))
    check_cpu(allowed[0])
    with pytest.raises(ValueError, match=rf"CPU {max(allowed) + 1} is not one this process may run on"):
        check_cpu(max(allowed) + 1)


def test_young_collections_run_between_ticks_once_the_allocator_asks_for_them(restored):
    gc.disable()
    gc.collect()
    between = GcBetweenTicks()
    between()
    assert between.collections == [0, 0, 0]
    kept = [[] for _ in range(between.threshold0 + 10)]  # containers count toward generation 0
    between()
    assert between.collections == [1, 0, 0]
    assert gc.get_count()[0] < between.threshold0
    del kept


PIN_CHILD = """
import json, os, sys, threading
from humanoid_prime.runtime.realtime import enter_realtime, leave_realtime
cpu = int(sys.argv[1])
ready, done = threading.Event(), threading.Event()
helper = threading.Thread(target=lambda: (ready.set(), done.wait()))
helper.start()
ready.wait()
report = enter_realtime(0.02, cpu=cpu, memory_refused=None)
later = threading.Thread(target=done.wait)
later.start()
threads = {t.name: sorted(os.sched_getaffinity(t.native_id)) for t in (threading.current_thread(), helper, later)}
done.set()
leave_realtime(report)
print(json.dumps({"cpu": report.cpu, "threads": threads}))
"""


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to tell pinned from free")
def test_with_a_cpu_the_loop_and_every_thread_that_shares_its_interpreter_lock_run_on_it():
    cpu = max(os.sched_getaffinity(0))
    result = subprocess.run([sys.executable, "-c", PIN_CHILD, str(cpu)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["cpu"] == cpu
    assert report["threads"] and all(cpus == [cpu] for cpus in report["threads"].values()), report


RAISE_CHILD = """
import json, os, threading
from humanoid_prime.runtime.realtime import enter_realtime, leave_realtime
ready, done = threading.Event(), threading.Event()
helper = threading.Thread(target=lambda: (ready.set(), done.wait()))
helper.start()
ready.wait()
report = enter_realtime(0.02, memory_refused=None)
during = os.sched_getscheduler(helper.native_id), os.sched_getparam(helper.native_id).sched_priority
leave_realtime(report)
after = os.sched_getscheduler(helper.native_id)
done.set()
print(json.dumps({"loop": report.scheduling, "during": during, "after": after}))
"""


def test_the_threads_beside_the_loop_run_real_time_below_it_while_it_runs():
    """A thread at normal priority that a busy host preempts while it holds the interpreter lock keeps the loop
    waiting for the lock; beside a real-time loop it runs real-time too, below the loop, and back after."""
    result = subprocess.run([sys.executable, "-c", RAISE_CHILD], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    if report["loop"] == "SCHED_OTHER":
        pytest.skip("real-time scheduling is not permitted here")
    policy, priority = report["during"]
    assert policy & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO and priority == realtime.OTHERS_PRIORITY
    assert report["after"] == os.SCHED_OTHER
