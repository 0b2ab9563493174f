"""The bad-input suite's totals by class, printed at the end of the run."""

from __future__ import annotations

import pytest

from cli.bad_input.cases import fill
from cli.bad_input.harness import CLASSES, TOTALS


@pytest.fixture
def folder(tmp_path):
    """A case's folder with the input files every case may name (``cases.fill``)."""
    fill(tmp_path)
    return tmp_path


def pytest_terminal_summary(terminalreporter) -> None:
    if sum(TOTALS.values()):
        counts = ", ".join(f"{kind} {TOTALS[kind]}" for kind in CLASSES)
        terminalreporter.write_line(f"bad input: {sum(TOTALS.values())} cases: {counts}")
