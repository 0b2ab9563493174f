"""`prime bench soak`, end to end on the virtual Prime: every fault of both buses injected once and judged, all
five modes visited with the remote stream, and nothing left behind."""

import json
import subprocess
import sys

import pytest

from humanoid_prime.bench.soak import FAULTS
from humanoid_prime.cli.bench import soak_failures
from humanoid_prime.modes import Mode
from humanoid_prime.virtual.netns import netns_unavailable_reason

REASON = netns_unavailable_reason()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(REASON is not None, reason=f"emulated soak: {REASON}")]


@pytest.fixture(scope="module")
def soak(tmp_path_factory) -> tuple[subprocess.CompletedProcess, dict]:
    out = tmp_path_factory.mktemp("soak") / "soak.json"
    # one pass of every fault, however long recoveries take on a loaded machine (4 minutes at most)
    proc = subprocess.run([sys.executable, "-m", "humanoid_prime", "bench", "soak", "--minutes", "4", "--no-load",
                           "--faults-once", "--fault-every", "2", "--dwell", "2", "--output", str(out)],
                          capture_output=True, text=True, timeout=420)
    return proc, json.loads(out.read_text())


def test_every_fault_of_both_buses_is_injected_and_does_what_it_should(soak):
    proc, result = soak
    assert [i["fault"] for i in result["injections"]] == [f.name for f in FAULTS]
    assert result["not_injected"] == []
    assert [i for i in result["injections"] if not i["as_designed"]] == []
    assert result["injector_error"] is None


def test_the_exit_status_is_1_exactly_when_the_report_lists_a_failure(soak):
    proc, result = soak
    failures = soak_failures(result)  # overruns among them: injected frame losses can still stall a tick
    assert proc.returncode == (1 if failures else 0), proc.stdout + proc.stderr
    assert all(f"soak: {failure}" in proc.stdout.replace("\n", " ") or failure[:40] in proc.stdout
               for failure in failures)


def test_no_fault_appears_that_nobody_injected(soak):
    _, result = soak
    assert result["unexpected_faults"] == []


def test_all_five_modes_run_with_the_remote_stream(soak):
    _, result = soak
    assert set(result["modes_visited"]) == {m.value for m in Mode}
    # one command per tick of the loop (the gate reset's ticks after it publish none)
    assert result["counters"]["stream_published"] >= 0.95 * result["ticks"]


def test_the_soak_leaves_every_gate_reset_and_every_drive_disabled(soak):
    _, result = soak
    assert result["gate_reset_failures"] == [] and result["gates_left_set"] == []
    assert result["drives_left_enabled"] == []
    assert result["problems_at_end"] == []


def test_the_report_says_what_each_fault_did(soak):
    proc, result = soak
    assert "faults injected" in proc.stdout
    assert f"{result['ticks']} ticks at 50 Hz" in proc.stdout
    assert "slave lost and returned" in proc.stdout


def test_the_output_keeps_every_flag_with_its_words_and_times(soak):
    _, result = soak
    flags = {(f["key"], f["since_s"]) for f in result["flags"]}
    for injection in result["injections"]:
        for key in injection["flags"]:  # each flag an injection was judged by can be read back
            assert any(k == key and s >= injection["at_s"] for k, s in flags), key
    assert all(f["text"] and f["level"] in ("WARN", "ERROR") and (f["until_s"] is None or f["until_s"] >= f["since_s"])
               for f in result["flags"])
