"""`prime ec scan` and `prime ec sdo read|write` on the IgH backend (fake `ethercat` tool on PATH)."""

from __future__ import annotations

import json

import pytest

from doubles.igh import FakeIgh
from humanoid_prime.cli import main
from humanoid_prime.cli.ec import parse_address
from humanoid_prime.errors import PrimeError


@pytest.fixture
def igh(tmp_path, monkeypatch):
    return FakeIgh(tmp_path / "bin", monkeypatch)


def test_an_address_is_index_and_subindex_in_hex():
    assert parse_address("0x2382:01") == (0x2382, 1)
    assert parse_address("603F:0") == (0x603F, 0)
    assert parse_address("0x2383") == (0x2383, 0)


def test_a_malformed_address_is_one_clear_error():
    with pytest.raises(PrimeError, match=r"'0x60zz:1' is not INDEX:SUB in hex"):
        parse_address("0x60zz:1")


def test_scan_lists_every_slave_with_identity_state_statusword_and_error(igh, capsys):
    igh.set(3, 0x6041, 0, 4616, "uint16")
    igh.set(3, 0x603F, 0, 0xA000, "uint16")
    igh.save()
    assert main(["ec", "scan", "--backend", "igh", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ring_matches"] and report["problem"] is None
    ring3 = report["slaves"][3]
    assert ring3["joint"] == "left_elbow_pitch"
    assert (ring3["vendor_id"], ring3["product_code"], ring3["al_state"]) == ("0x5A65726F", "0x00029252", "OP")
    assert (ring3["statusword"], ring3["drive_state"]) == (4616, "fault")
    assert (ring3["error_code"], ring3["error"]) == ("0xA000", "EtherCAT communication error")
    assert report["slaves"][4]["joint"] == "left_wrist_yaw"
    assert report["slaves"][0]["drive_state"] == "operation enabled"


def test_scan_of_a_mismatched_ring_reports_found_versus_expected_and_exits_1(igh, capsys):
    igh.state["slaves"][7]["product"] = 0x1234
    igh.save()
    assert main(["ec", "scan", "--backend", "igh"]) == 1
    out = capsys.readouterr().out
    assert "problem: EtherCAT ring on IgH master 0 does not match" in out
    assert "ring 7: expected right_shoulder_yaw" in out


def test_sdo_read_prints_the_value_in_decimal_and_hex(igh, capsys):
    igh.set(2, 0x2382, 1, 30, "uint32")
    igh.save()
    assert main(["ec", "sdo", "read", "2", "0x2382:01", "--type", "u32", "--backend", "igh"]) == 0
    assert capsys.readouterr().out == "ring 2 0x2382:01 = 30 (0x0000001E, uint32)\n"


def test_sdo_read_json_names_the_object_and_the_type(igh, capsys):
    assert main(["ec", "sdo", "read", "0", "0x6041:0", "--backend", "igh", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {
        "ring": 0, "index": "0x6041", "sub_index": 0, "backend": "igh", "type": "uint16", "value": 5687,
        "hex": "0x1637"}


def test_sdo_write_downloads_and_reads_back(igh, capsys):
    igh.set(5, 0x2383, 0, 0, "uint8")
    igh.save()
    assert main(["ec", "sdo", "write", "5", "0x2383:0", "1", "--type", "u8", "--backend", "igh"]) == 0
    assert igh.value(5, 0x2383, 0) == 1
    assert capsys.readouterr().out == "ring 5 0x2383:00 <- 1; read back 1 (0x01)\n"


def test_sdo_write_without_a_type_keeps_the_object_size(igh):
    igh.set(5, 0x2381, 1, 94, "uint16")
    igh.save()
    assert main(["ec", "sdo", "write", "5", "0x2381:1", "56", "--backend", "igh"]) == 0
    assert "-m 0 download -p5 0x2381 0x01 56 --type uint16" in igh.calls


def test_an_sdo_abort_is_one_line_on_stderr_and_exit_1(igh, capsys):
    assert main(["ec", "sdo", "read", "1", "0x7000:0", "--backend", "igh"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("prime ec: SDO 0x7000:00 on ring 1: `ethercat upload -p1 0x7000 0x00` failed (exit 1): "
                          "SDO transfer aborted with code 0x06020000")


def test_a_ring_position_off_the_ring_is_refused(igh, capsys):
    assert main(["ec", "sdo", "read", "12", "0x6041:0", "--backend", "igh"]) == 1
    assert "ring position 12 is not on the ring" in capsys.readouterr().err


def test_a_bad_value_is_refused_before_any_bus_access(igh, capsys):
    assert main(["ec", "sdo", "write", "1", "0x2383:0", "one", "--backend", "igh"]) == 1
    assert "VALUE 'one' is not an integer" in capsys.readouterr().err
    assert igh.calls == []


def test_scan_reads_the_error_history_newest_first(igh, capsys):
    for position in range(10):
        igh.set(position, 0x1003, 0, 0, "uint8")
    igh.set(3, 0x1003, 0, 2, "uint8")
    igh.set(3, 0x1003, 1, 0x00018500, "uint32")
    igh.set(3, 0x1003, 2, 0xA000, "uint32")
    igh.save()
    assert main(["ec", "scan", "--backend", "igh", "--history", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["slaves"][3]["error_history"] == ["0x8500", "0xA000"]
    assert report["slaves"][0]["error_history"] == []
