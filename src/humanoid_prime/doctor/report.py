"""What ``prime doctor`` found: one ``Check`` per line, grouped host, EtherCAT, CAN, robot; the report prints the
same checks as text or as JSON, so the two always agree.

A check says pass, warn or fail, what was found, and the fix (a command, or a file and key). A check that could
not run is a warn with ``ran`` false, and its text says why it could not run.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

GROUPS = {"host": "host", "ethercat": "EtherCAT", "can": "CAN", "robot": "robot"}  # key -> heading, in order


class Verdict(StrEnum):
    PASS = "pass"
    WARN = "warn"
    FAIL = "fail"


@dataclass(frozen=True)
class Check:
    group: str  # a key of GROUPS
    name: str  # e.g. "nic.carrier"; unique within its group
    verdict: Verdict
    found: str
    fix: str | None = None
    ran: bool = True

    def __post_init__(self) -> None:
        if self.group not in GROUPS:
            raise ValueError(f"unknown check group {self.group!r}")

    @property
    def id(self) -> str:
        return f"{self.group}.{self.name}"

    def as_dict(self) -> dict[str, object]:
        return {"id": self.id, "group": self.group, "name": self.name, "verdict": self.verdict.value,
                "found": self.found, "fix": self.fix, "ran": self.ran}

    def line(self, width: int = 0) -> str:
        text = f"  {self.verdict.value}  {self.name:<{width}}  {self.found}"
        return text + (f"  fix: {self.fix}" if self.fix else "")


def passed(group: str, name: str, found: str) -> Check:
    return Check(group, name, Verdict.PASS, found)


def warned(group: str, name: str, found: str, fix: str | None = None) -> Check:
    return Check(group, name, Verdict.WARN, found, fix)


def failed(group: str, name: str, found: str, fix: str | None = None) -> Check:
    return Check(group, name, Verdict.FAIL, found, fix)


def not_run(group: str, name: str, why: str, fix: str | None = None) -> Check:
    """A check that could not run, and why (a warn: nothing is known about what it checks)."""
    return Check(group, name, Verdict.WARN, f"not checked: {why}", fix, ran=False)


@dataclass
class Report:
    checks: list[Check] = field(default_factory=list)
    context: dict[str, object] = field(default_factory=dict)  # what was checked: files, interfaces, rates
    seconds: dict[str, float] = field(default_factory=dict)

    def add(self, *checks: Check) -> None:
        self.checks.extend(checks)

    def count(self, verdict: Verdict) -> int:
        return sum(1 for c in self.checks if c.verdict is verdict)

    @property
    def not_run(self) -> list[Check]:
        return [c for c in self.checks if not c.ran]

    @property
    def ok(self) -> bool:
        """Nothing failed (the command's exit status is 0 exactly then)."""
        return self.count(Verdict.FAIL) == 0

    def ordered(self) -> list[Check]:
        """The checks group by group (host, EtherCAT, CAN, robot), each group in the order its checks ran."""
        order = list(GROUPS)
        return sorted(self.checks, key=lambda c: order.index(c.group))

    def summary_line(self) -> str:
        took = sum(self.seconds.values())
        unchecked = len(self.not_run)
        return (f"{self.count(Verdict.FAIL)} failed, {self.count(Verdict.WARN)} warned"
                + (f" ({unchecked} of them not checked)" if unchecked else "")
                + f", {self.count(Verdict.PASS)} passed in {took:.1f} s")

    def lines(self) -> list[str]:
        out: list[str] = []
        width = max((len(c.name) for c in self.checks), default=0)
        group = None
        for check in self.ordered():
            if check.group != group:
                group = check.group
                out.append(GROUPS[group])
            out.append(check.line(width))
        out.append(self.summary_line())
        return out

    def as_dict(self) -> dict[str, object]:
        return {"ok": self.ok, "failed": self.count(Verdict.FAIL), "warned": self.count(Verdict.WARN),
                "passed": self.count(Verdict.PASS), "not_checked": [c.id for c in self.not_run],
                "checks": [c.as_dict() for c in self.ordered()], "context": self.context,
                "seconds": {k: round(v, 3) for k, v in self.seconds.items()}}
