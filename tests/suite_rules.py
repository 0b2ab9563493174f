"""The suite's rules (docs/development.md, Tests), a plugin of the root conftest.

Two groups. Tests marked ``realtime`` (every ``netns`` test is one: it starts the emulated robot on the wall clock)
run in the real-time lanes: the first ``PRIME_SUITE_REALTIME_LANES`` workers of a parallel run (pytest-xdist,
``-n N``; default 1, ``make test`` 2), each running one test at a time, and nothing else until no real-time test is
left. The other tests run on the other workers, niced (``PARALLEL_NICE``), and on the lanes once they are done.

A worker is handed a unit of work at a time (``_unit``): a test alone, or every test of its module where they share
a module fixture, so that it is set up once. pytest-xdist's own ``loadgroup`` marks its groups by renaming tests,
which pytest 9.2 no longer sees; the units travel from the workers' collection to the scheduler in a file.

A test outside the real-time group that runs a command only a real-time test may run (``GUARDED``), itself or
through a command it starts, fails with the marker it needs. With ``CI=true`` a skipped test fails: a skip there
hides a capability the CI machine lacks (root or user namespaces, real-time scheduling, a second CPU)."""

from __future__ import annotations

import json
import os
import shutil
import stat
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

IN_CI = os.environ.get("CI", "").lower() in ("true", "1", "yes")
REALTIME = "realtime"
LANES = int(os.environ.get("PRIME_SUITE_REALTIME_LANES", "1"))
# Commands only a real-time test may run, and why.
GUARDED = {
    "unshare": "starts a network namespace (the emulated robot runs on the wall clock)",
    "stress-ng": "loads the cores (it would slow the tests running beside it)",
    "cyclictest": "measures the machine's real-time latency",
}
GUARD_LOG = "PRIME_SUITE_GUARD_LOG"
# Niceness of a parallel worker once it runs a test outside the real-time group (and of every process it starts): the
# real-time group's processes, at normal priority beside their real-time threads, get three times a worker's share of
# a busy CPU (a thread of the emulated robot that waits behind busy workers for its interpreter lock misses the
# drives' 100 ms watchdog), and the workers still get on beside a machine's other work.
PARALLEL_NICE = 5


def pytest_configure(config: pytest.Config) -> None:
    _guard_commands()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """``netns`` tests are real-time tests. A parallel worker leaves each test's unit where the scheduler reads it."""
    for item in items:
        if item.get_closest_marker("netns") is not None and item.get_closest_marker(REALTIME) is None:
            item.add_marker(pytest.mark.realtime)
    workerinput = getattr(config, "workerinput", None)
    if workerinput is not None:
        units = _units_path(workerinput["testrunuid"])
        written = units.with_suffix(f".{workerinput['workerid']}")
        written.write_text(json.dumps({item.nodeid: _unit(item) for item in items}))
        os.replace(written, units)  # every worker collects the same tests: whichever is last stays


def _unit(item: pytest.Item) -> str:
    """The unit of work of ``item``: its module where it uses a fixture set up once per module (or class), else
    the test alone; prefixed with the group for a real-time test."""
    defs = getattr(getattr(item, "_fixtureinfo", None), "name2fixturedefs", None)  # pytest's: no public way
    shared = defs is None or any(d.scope in ("module", "class", "package") for ds in defs.values() for d in ds)
    unit = item.nodeid.split("::", 1)[0] if shared else item.nodeid
    return f"{REALTIME}:{unit}" if item.get_closest_marker(REALTIME) is not None else unit


def _units_path(testrunuid: str) -> Path:
    return Path(tempfile.gettempdir()) / f"prime-suite-units-{testrunuid}.json"


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """``pytest -n N`` (pytest-xdist's default distribution): the units of work (``_unit``), the real-time ones only
    to the lanes, largest first."""
    if config.getvalue("dist") != "load":
        return None  # a distribution asked for by name
    from xdist.scheduler import LoadScopeScheduling

    class GroupScheduling(LoadScopeScheduling):
        units: dict[str, str] | None = None

        def schedule(self) -> None:
            if self.units is None and self.nodes:
                path = _units_path(self.nodes[0].workerinput["testrunuid"])
                self.units = json.loads(path.read_text())
                path.unlink()
            super().schedule()

        def _split_scope(self, nodeid: str) -> str:
            return (self.units or {}).get(nodeid, nodeid)

        def remove_node(self, node) -> str | None:
            # pytest-xdist puts every unit of a crashed worker back in the queue, finished ones too; a worker handed
            # one would wait for tests that never come, and the run with it
            workload = self.assigned_work.get(node, {})
            for unit in [unit for unit, tests in workload.items() if all(tests.values())]:
                del workload[unit]
            return super().remove_node(node)

        def _assign_work_unit(self, node) -> None:
            lane = node in self.nodes[:max(1, LANES)]
            for unit in self.workqueue:  # largest first (pytest-xdist orders them by their number of tests)
                if unit.startswith(REALTIME) == lane:
                    self.workqueue.move_to_end(unit, last=False)
                    break
            else:
                if not lane:
                    return  # the lanes will run what is left
            super()._assign_work_unit(node)

    return GroupScheduling(config, log)


@pytest.fixture(autouse=True)
def parallel_priority(request: pytest.FixtureRequest) -> None:
    """On a parallel worker, a test outside the real-time group runs niced (``PARALLEL_NICE``); a lane runs its
    real-time tests first, so it is niced only after them (niceness is never lowered again)."""
    if (os.environ.get("PYTEST_XDIST_WORKER") and request.node.get_closest_marker(REALTIME) is None
            and os.getpriority(os.PRIO_PROCESS, 0) < PARALLEL_NICE):
        os.setpriority(os.PRIO_PROCESS, 0, PARALLEL_NICE)


def _guard_commands() -> None:
    """A wrapper per guarded command, ahead of it on the PATH: it appends its command line to the file named by
    ``PRIME_SUITE_GUARD_LOG`` (set while a test outside the real-time group runs) and runs the real command."""
    prefix = "prime-suite-guard-"
    path = os.pathsep.join(p for p in os.environ.get("PATH", "").split(os.pathsep) if prefix not in p)  # a suite's
    folder = Path(tempfile.mkdtemp(prefix=prefix))  # own, not those of a suite that started this one
    for name in GUARDED:
        real = shutil.which(name, path=path)
        if real is None:
            continue  # missing: the tests that need it say so
        wrapper = folder / name
        wrapper.write_text(f'#!/bin/sh\n[ -n "${GUARD_LOG}" ] && echo "{name} $*" >> "${GUARD_LOG}"\n'
                           f'exec {real} "$@"\n')
        wrapper.chmod(wrapper.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    os.environ["PATH"] = f"{folder}{os.pathsep}{path}"


@pytest.fixture(autouse=True)
def guarded_commands(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory,
                     monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """A test outside the real-time group fails if it, or a command it started, ran a guarded command."""
    if request.node.get_closest_marker(REALTIME) is not None:
        monkeypatch.delenv(GUARD_LOG, raising=False)
        yield
        return
    log = tmp_path_factory.getbasetemp() / f"guard-{uuid.uuid4().hex}.log"
    monkeypatch.setenv(GUARD_LOG, str(log))
    yield
    if log.exists():
        ran = log.read_text().splitlines()
        log.unlink()
        why = "; ".join(sorted({GUARDED[line.split(" ", 1)[0]] for line in ran}))
        pytest.fail(f"this test {why}: `{ran[0]}`. Mark it `@pytest.mark.realtime` (or `netns`), so it runs in the "
                    "real-time group, one test at a time (docs/development.md, Tests)", pytrace=False)


def _reason(longrepr: object) -> str:
    text = longrepr[2] if isinstance(longrepr, tuple) else str(longrepr)
    return str(text).removeprefix("Skipped: ")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    """With CI=true a skipped test fails, naming what the machine lacks."""
    outcome = yield
    report = outcome.get_result()
    if IN_CI and report.skipped and not hasattr(report, "wasxfail"):
        report.outcome = "failed"
        report.longrepr = (f"CI=true: skipped ({_reason(report.longrepr)}); a CI machine must provide what the test "
                           "needs, or the skip hides a test that never runs")


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector: pytest.Collector) -> Iterator[None]:
    """With CI=true a module that skips itself at import fails to collect, naming what the machine lacks."""
    outcome = yield
    report = outcome.get_result()
    if IN_CI and report.skipped:
        report.outcome = "failed"
        report.longrepr = (f"CI=true: {collector.nodeid} skipped at import ({_reason(report.longrepr)}); a CI "
                           "machine must provide what its tests need")
