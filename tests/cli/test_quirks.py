"""The virtual Prime with the quirks real slaves have (virtual/ring/quirks.py), each profile and all at once: a
bring-up through STANDBY, DAMPING and STANDBY with every gain switch, `prime ec scan` and `prime ec sdo write/read`,
each fully up. Then the way back: SOEM alone working the mailboxes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from humanoid_prime.cli import main
from humanoid_prime.files import bundled
from humanoid_prime.virtual.netns import EmulatedRing, netns_unavailable_reason
from humanoid_prime.virtual.ring.quirks import ALL, PROFILES

REASON = netns_unavailable_reason()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(REASON is not None, reason=f"no emulated ring: {REASON}")]
EACH_AND_ALL = [*PROFILES, ALL]
SEQUENCE = ["STANDBY", "DAMPING", "STANDBY"]
# a reply dropped as unrecognised, malformed or for another object is a quirk misread (a late one: see below)
NOTHING_DROPPED = {"late": 0, "other object": 0, "unrecognised": 0, "malformed": 0}


def bringup(tmp_path: Path, *args: str) -> dict:
    summary = tmp_path / "summary.json"
    proc = subprocess.run([sys.executable, "-m", "humanoid_prime", "bringup", "--emulate", "--no-live", "--summary",
                           str(summary), "--socket", str(tmp_path / "control.sock"), "--sequence",
                           ",".join(SEQUENCE), "--dwell", "0.3", *args],
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr
    return json.loads(summary.read_text())


def assert_nothing_misread(drops: dict) -> None:
    """Every reply understood, none for another object. A reply that a quirk makes unrecognisable (reserved bits, a
    counter, a size left out) fails the match on what identifies it, so it counts as unrecognised or for another
    object, never as late. A late one answers an earlier request that matched it: one this host gave up on (asked
    again, or timed out), a read of SOEM's at start-up whose late reply was taken for ours, which reads the same
    object, before ours came; on a busy host both happen, and neither is a quirk misread."""
    assert drops == {**NOTHING_DROPPED, "late": drops["late"]}, drops


def assert_up_with_every_switch(summary: dict) -> None:
    assert summary["ok"], summary["problems"]
    assert (summary["end"]["slaves_op"], summary["end"]["drives_enabled"]) == (10, 10)
    switches = [(s["mode"], s["ok"]) for s in summary["mode_switches"]]
    # the start-up mode (ZERO_TORQUE, latched) is a switch of its own unless the sequence's first one overtook it
    assert switches[-3:] == [(mode, True) for mode in SEQUENCE] and all(ok for _mode, ok in switches), switches
    assert all(s["failed"] == {} for s in summary["mode_switches"])


@pytest.mark.parametrize("quirks", EACH_AND_ALL)
def test_a_bring_up_switches_standby_damping_standby_on_every_drive(tmp_path, quirks):
    summary = bringup(tmp_path, "--quirks", quirks)
    assert_up_with_every_switch(summary)
    drops = summary["ethercat_bringup"]["mailbox_drops"]
    assert summary["ethercat_bringup"]["mailbox"] == "prime"
    assert_nothing_misread(drops)


@pytest.mark.parametrize("quirks", EACH_AND_ALL)
def test_scan_and_sdo_write_and_read_reach_op_and_every_drive(quirks, capsys):
    with EmulatedRing(slaves=10, quirks=quirks) as ring:
        interface = ring.master_interface
        assert main(["ec", "scan", "--interface", interface, "--json"]) == 0
        report = json.loads(capsys.readouterr().out)
        assert report["problem"] is None and [s["al_state"] for s in report["slaves"]] == ["OP"] * 10
        assert [s["rated_torque_nm"] for s in report["slaves"]] == [23.0] * 10  # 0x6076, a 4-byte value
        assert_nothing_misread(report["mailbox_drops"])
        assert main(["ec", "sdo", "write", "6", "0x2383:0", "1", "--interface", interface]) == 0  # the gain gate
        capsys.readouterr()
        assert main(["ec", "sdo", "write", "6", "0x2382:01", "515", "--interface", interface, "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["value"] == 515
        assert main(["ec", "sdo", "read", "6", "0x2382:01", "--interface", interface, "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["value"] == 515
        assert ring.control.slave(6)["drive"]["pos_reg"] == 515


def test_the_way_back_soem_alone_works_the_mailboxes_through_a_whole_bring_up(tmp_path):
    summary = bringup(tmp_path, "--ec-mailbox", "soem")
    assert_up_with_every_switch(summary)
    assert summary["ethercat_bringup"]["mailbox"] == "soem"


def test_the_hardware_file_key_alone_hands_the_mailboxes_to_soem(tmp_path, capsys):
    hardware = yaml.safe_load(bundled("prime_hardware.yaml").read_text())
    hardware["buses"]["ethercat"]["mailbox"] = "soem"
    path = tmp_path / "prime_hardware.yaml"
    path.write_text(yaml.safe_dump(hardware, sort_keys=False))
    with EmulatedRing(slaves=10, quirks=ALL) as ring:
        assert main(["ec", "scan", "--interface", ring.master_interface, "--hardware", str(path), "--json"]) == 0
        report = json.loads(capsys.readouterr().out)
        assert report["mailbox"] == "soem" and report["problem"] is None
        assert [s["rated_torque_nm"] for s in report["slaves"]] == [23.0] * 10
