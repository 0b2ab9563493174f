"""`prime ec scan` and `prime ec sdo` on the SOEM backend against the emulated ring (--interface override)."""

from __future__ import annotations

import json

import pytest

from humanoid_prime.cli import main
from humanoid_prime.virtual.netns import EmulatedRing, netns_unavailable_reason

REASON = netns_unavailable_reason()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(REASON is not None, reason=f"no emulated ring: {REASON}")]


@pytest.fixture(scope="module")
def ring():
    with EmulatedRing(slaves=10) as r:
        yield r


def test_scan_brings_the_ring_to_op_and_decodes_every_drive(ring, capsys):
    assert main(["ec", "scan", "--interface", ring.master_interface, "--history", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ring_matches"] and report["problem"] is None
    assert report["interface"] == ring.master_interface
    assert [s["al_state"] for s in report["slaves"]] == ["OP"] * 10
    assert {(s["statusword"], s["drive_state"], s["error_code"], s["error"]) for s in report["slaves"]} == {
        (592, "switch on disabled", "0x0000", "no error")}
    assert [s["joint"] for s in report["slaves"]][4] == "left_wrist_yaw"
    assert [s["error_history"] for s in report["slaves"]] == [[]] * 10
    assert [s["rated_torque_nm"] for s in report["slaves"]] == [23.0] * 10  # 0x6076, read in PRE-OP


def test_scan_names_each_drive_s_rated_torque(ring, capsys):
    assert main(["ec", "scan", "--interface", ring.master_interface]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert all("rated 23 N*m" in line for line in lines if line.lstrip().startswith("ring"))


def test_a_written_object_reads_back_in_a_later_session(ring, capsys):
    # no --type: written with the size the drive holds the gate in (UDINT)
    assert main(["ec", "sdo", "write", "6", "0x2383:0", "1", "--interface", ring.master_interface]) == 0
    assert capsys.readouterr().out == "ring 6 0x2383:00 <- 1; read back 1 (0x00000001)\n"
    assert main(["ec", "sdo", "read", "6", "0x2383:0", "--interface", ring.master_interface, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["value"] == 1
    assert ring.control.slave(6)["drive"]["gate"] == 1


def test_an_unknown_interface_is_one_line(capsys):
    assert main(["ec", "scan", "--interface", "nosuchnic0"]) == 1
    err = capsys.readouterr().err
    assert err == ("prime ec: no network interface 'nosuchnic0' (buses.ethercat.interface in prime_hardware.yaml); "
                   "list them with `ip link` or pass --interface\n")
