"""The bad-input suite's totals by class, printed at the end of the run."""

from __future__ import annotations

from cli.bad_input.harness import CLASSES, TOTALS


def pytest_terminal_summary(terminalreporter) -> None:
    if sum(TOTALS.values()):
        counts = ", ".join(f"{kind} {TOTALS[kind]}" for kind in CLASSES)
        terminalreporter.write_line(f"bad input: {sum(TOTALS.values())} cases: {counts}")
