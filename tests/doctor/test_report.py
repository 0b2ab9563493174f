"""The report: grouped host, EtherCAT, CAN, robot; one line per check; JSON with the same checks and verdicts."""

from __future__ import annotations

import re

from humanoid_prime.doctor.report import Report, Verdict, failed, not_run, passed, warned

LINE = re.compile(r"^  (pass|warn|fail)  (\S+)\s+(.*)$")


def report() -> Report:
    r = Report()
    r.add(passed("robot", "calibration", "calibrated"), failed("host", "nic.carrier", "no carrier on eth1", "plug it"),
          not_run("ethercat", "scan", "no carrier on eth1"), warned("host", "kernel", "not PREEMPT_RT", "boot one"))
    r.seconds = {"host": 1.0, "ethercat": 0.5}
    return r


def test_lines_come_grouped_host_ethercat_can_robot_with_the_fix_on_the_line():
    assert report().lines() == [
        "host",
        "  fail  nic.carrier  no carrier on eth1  fix: plug it",
        "  warn  kernel       not PREEMPT_RT  fix: boot one",
        "EtherCAT",
        "  warn  scan         not checked: no carrier on eth1",
        "robot",
        "  pass  calibration  calibrated",
        "1 failed, 2 warned (1 of them not checked), 1 passed in 1.5 s",
    ]


def test_the_json_holds_the_same_checks_and_verdicts_as_the_lines():
    r = report()
    shown = [(m[2], m[1]) for m in (LINE.match(line) for line in r.lines()) if m]
    data = r.as_dict()
    assert [(c["name"], c["verdict"]) for c in data["checks"]] == shown
    assert data["ok"] is False and data["not_checked"] == ["ethercat.scan"]
    assert (data["failed"], data["warned"], data["passed"]) == (1, 2, 1)


def test_only_a_failure_makes_the_report_not_ok():
    r = Report()
    r.add(warned("host", "kernel", "not PREEMPT_RT"), not_run("can", "link", "virtual"))
    assert r.ok and r.count(Verdict.WARN) == 2
