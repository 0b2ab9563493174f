"""The suite's own rules (tests/conftest.py), on small suites run in a child pytest with the same conftest: with
CI=true a skip fails and says why; a test outside the real-time group that starts a network namespace, loads the
cores or measures the machine's latency fails and names the marker it needs."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from suite_rules import GUARD_LOG

TESTS = Path(__file__).parent


def run_suite(tmp_path: Path, source: str, *args: str, ci: bool) -> subprocess.CompletedProcess:
    (tmp_path / "test_example.py").write_text(textwrap.dedent(source))
    env = {k: v for k, v in os.environ.items()
           if k not in ("CI", "PYTEST_XDIST_WORKER", "PYTEST_XDIST_WORKER_COUNT", "PYTEST_ADDOPTS", GUARD_LOG)}
    env.update(PYTHONPATH=str(TESTS), PRIME_SUITE_REALTIME_LANES="1", **({"CI": "true"} if ci else {}))
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "suite_rules", "-p", "no:cacheprovider", *args,
                           "--rootdir", str(tmp_path), "-c", str(TESTS.parent / "pyproject.toml"), str(tmp_path)],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env)


SKIPS = """
    import pytest

    def test_skips_in_its_body():
        pytest.skip("no network namespace here")

    @pytest.mark.skipif(True, reason="needs two CPUs")
    def test_skipped_by_its_marker():
        pass

    @pytest.mark.xfail(reason="a known bug", strict=True)
    def test_an_expected_failure():
        assert False
"""


def test_a_skip_is_a_skip_outside_ci(tmp_path):
    done = run_suite(tmp_path, SKIPS, ci=False)
    assert done.returncode == 0, done.stdout
    assert "2 skipped, 1 xfailed" in done.stdout


def test_with_ci_true_a_skip_fails_and_says_what_the_machine_lacks(tmp_path):
    done = run_suite(tmp_path, SKIPS, ci=True)
    assert done.returncode == 1, done.stdout
    assert "1 failed, 1 xfailed, 1 error" in done.stdout  # a marker's skip happens at setup: an error there
    assert "CI=true: skipped (no network namespace here)" in done.stdout
    assert "CI=true: skipped (needs two CPUs)" in done.stdout


def test_with_ci_true_a_module_that_skips_at_import_fails(tmp_path):
    done = run_suite(tmp_path, """
        import pytest

        pytest.skip("emulated bringup: not root", allow_module_level=True)

        def test_never_collected():
            pass
    """, ci=True)
    assert done.returncode != 0, done.stdout
    assert "skipped at import (emulated bringup: not root)" in done.stdout


@pytest.mark.parametrize("command", ["unshare", "stress-ng", "cyclictest"])
def test_a_guarded_command_outside_the_realtime_group_fails_the_test_and_names_the_marker(tmp_path, command):
    if shutil.which(command) is None:
        pytest.fail(f"{command} is not installed (make test installs what the tests use)")
    done = run_suite(tmp_path, f"""
        import subprocess

        import pytest

        def test_unmarked():
            subprocess.run(["{command}", "--help"], capture_output=True)

        @pytest.mark.realtime
        def test_marked_realtime():
            subprocess.run(["{command}", "--help"], capture_output=True)

        @pytest.mark.netns
        def test_marked_netns():
            subprocess.run(["{command}", "--help"], capture_output=True)
    """, ci=False)
    assert "3 passed, 1 error" in done.stdout, done.stdout
    assert "ERROR at teardown of test_unmarked" in done.stdout
    assert f"`{command} --help`. Mark it `@pytest.mark.realtime`" in done.stdout


def test_a_worker_that_dies_costs_its_test_and_the_run_goes_on_to_the_end(tmp_path):
    """A crashed worker's finished units are not handed out again: a worker given one would wait for nothing, and
    the whole run with it."""
    done = run_suite(tmp_path, """
        import os
        import time

        import pytest

        @pytest.mark.realtime
        @pytest.mark.parametrize("k", range(4))
        def test_realtime(k):
            time.sleep(0.2)

        @pytest.mark.realtime
        def test_crashes_its_worker_once(tmp_path_factory):
            once = tmp_path_factory.getbasetemp().parent / "crashed"
            if not once.exists():
                once.touch()
                os._exit(3)

        @pytest.mark.parametrize("k", range(8))
        def test_other(k):
            time.sleep(0.1)
    """, "-n", "2", ci=False)
    assert "crashed while running 'test_example.py::test_crashes_its_worker_once'" in done.stdout, done.stdout
    assert "1 failed, 13 passed" in done.stdout, done.stdout
