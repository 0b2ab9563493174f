"""A busy robot computer: other work on every core while a test runs (stress-ng, installed by `make test`)."""

from __future__ import annotations

import contextlib
import shutil
import subprocess
from collections.abc import Iterator

import pytest


@contextlib.contextmanager
def busy_cores(workers: int) -> Iterator[None]:
    """``workers`` stress-ng CPU workers at normal priority for the duration of the block."""
    if shutil.which("stress-ng") is None:
        pytest.fail("stress-ng is not installed (make test installs it: tools/install-debs stress-ng)")
    process = subprocess.Popen(["stress-ng", "--cpu", str(workers), "--quiet"], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    try:
        yield
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
