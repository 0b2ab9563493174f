"""`prime bringup` tells the truth about faults in its exit status and summary (on the doubles, in-process:
the eRob ring on the master double, the wrists on emulated motors over a private virtual CAN channel)."""

from __future__ import annotations

import contextlib
import json
import threading

from humanoid_prime.cli import main
from humanoid_prime.errors import PrimeError
from humanoid_prime.runtime.socket import request


def bringup(doubled, tmp_path, *extra: str) -> int:
    return main(["bringup", "--no-live", "--uncalibrated", "--duration", "1.0", "--can-interface", "virtual",
                 "--can-channel",
                 doubled.channel, "--socket", str(tmp_path / "sock"), "--summary", str(tmp_path / "summary.json"),
                 *extra])


def fault_when_up(doubled, tmp_path, position: int, code: int) -> threading.Thread:
    """Fault one drive of the master double once the run is up (its control socket says ready)."""
    def ready() -> bool:
        with contextlib.suppress(PrimeError):
            return request(tmp_path / "sock", {"op": "ping"}, timeout=0.5)["ready"]
        return False

    def inject() -> None:
        while not ready():
            threading.Event().wait(0.01)
        doubled.master.fault(position, code)

    thread = threading.Thread(target=inject, daemon=True)
    thread.start()
    return thread


def test_a_clean_run_exits_0_and_says_so(doubled, tmp_path, capsys):
    assert bringup(doubled, tmp_path, "--mode", "STANDBY") == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["ok"] and summary["problems"] == []
    assert summary["end"]["slaves_op"] == 10 and summary["end"]["sito_online"] == 4


def test_a_drive_fault_makes_the_run_exit_1_with_the_fault_and_its_time_in_the_summary(doubled, tmp_path, capsys):
    injector = fault_when_up(doubled, tmp_path, 5, 0x8500)
    assert bringup(doubled, tmp_path, "--mode", "STANDBY") == 1
    injector.join(timeout=10)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert not summary["ok"]
    fault = next(f for f in summary["faults"] if f["key"].endswith("ethercat/ring5/fault"))
    assert fault["level"] == "ERROR" and "0x8500" in fault["text"] and fault["since_s"] > 0
    out, err = capsys.readouterr()
    assert "ERROR PrimeEtherCATSide/ethercat/ring5/fault at" in out
    (line,) = err.strip().splitlines()
    assert line.startswith("prime bringup: FAULTED: PrimeEtherCATSide/ethercat/ring5/fault at ")
