"""The IgH `ethercat` tool adapter, against a fake tool on PATH: command lines, output parsing, errors."""

from __future__ import annotations

import pytest

from doubles.igh import FakeIgh
from humanoid_prime.drivers.ethercat.errors import RingError, SdoError, SdoRefused
from humanoid_prime.drivers.ethercat.igh import IghSdo, parse_upload


@pytest.fixture
def igh(tmp_path, monkeypatch):
    return FakeIgh(tmp_path / "bin", monkeypatch)


def test_upload_output_is_parsed_as_hex_and_decimal():
    assert parse_upload("0x0000001e 30\n", "uint32") == (30, 4)


def test_a_negative_value_is_taken_from_the_decimal_column():
    assert parse_upload("0xffe2 -30\n", "int16") == (-30, 2)


def test_without_a_type_the_size_comes_from_the_hex_width():
    assert parse_upload("0x1637 5687\n", None) == (5687, 2)


def test_unexpected_output_is_refused():
    with pytest.raises(ValueError, match="expected '0x<hex> <decimal>'"):
        parse_upload("garbage\n", "uint16")


def test_an_upload_runs_the_documented_command_line(igh):
    igh.set(3, 0x2382, 1, 30, "uint32")
    igh.save()
    assert IghSdo().upload(3, 0x2382, 1, "uint32") == (30, 4)
    assert igh.calls[-1] == "-m 0 upload -p3 0x2382 0x01 --type uint32"


def test_sdo_read_returns_little_endian_bytes_of_the_dictionary_type(igh):
    assert IghSdo().sdo_read(0, 0x6041, 0) == (5687).to_bytes(2, "little")


def test_sdo_write_picks_the_type_from_the_data_length_and_reads_back(igh):
    igh.set(2, 0x2383, 0, 0, "uint8")
    igh.save()
    sdo = IghSdo()
    sdo.sdo_write(2, 0x2383, 0, b"\x01")
    assert igh.calls[-1] == "-m 0 download -p2 0x2383 0x00 1 --type uint8"
    assert sdo.sdo_read(2, 0x2383, 0) == b"\x01"


def test_an_sdo_abort_becomes_one_line_with_the_abort_code(igh):
    with pytest.raises(SdoError) as err:
        IghSdo().upload(1, 0x7000, 0, "uint16")
    assert err.value.abort_code == 0x06020000
    assert str(err.value) == ("SDO 0x7000:00 on ring 1: `ethercat upload -p1 0x7000 0x00 --type uint16` failed "
                              "(exit 1): SDO transfer aborted with code 0x06020000: This object does not exist "
                              "in the object directory.")


def test_a_master_that_is_not_running_is_one_clear_line(igh):
    igh.state["no_master"] = True
    igh.save()
    with pytest.raises(RingError, match=r"^`ethercat slaves -v` failed \(exit 1\): Failed to open master device "
                                        r"/dev/EtherCAT0: No such file or directory$"):
        IghSdo().sdo_read(0, 0x6041, 0)


def test_a_missing_tool_says_how_to_get_one(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(RingError, match="not on PATH: install the IgH EtherCAT master or use --backend soem"):
        IghSdo().sdo_read(0, 0x6041, 0)


def test_an_sdo_is_refused_while_slaves_are_being_activated(igh):
    igh.state["slaves"][4]["state"] = "SAFEOP"
    igh.save()
    with pytest.raises(SdoRefused, match=r"not settled \(slaves in OP, SAFEOP\).*0xA000"):
        IghSdo().sdo_read(0, 0x6041, 0)
    assert not any("upload" in call for call in igh.calls)


def test_an_idle_ring_in_preop_allows_commissioning(igh):
    for slave in igh.state["slaves"]:
        slave["state"] = "PREOP"
    igh.save()
    assert IghSdo().sdo_read(0, 0x6041, 0) == (5687).to_bytes(2, "little")


def test_the_slave_list_carries_identity_and_state(igh):
    slaves = IghSdo().slaves()
    assert len(slaves) == 10
    assert slaves[9].position == 9 and slaves[9].is_erob and slaves[9].al_state == 0x08
    assert slaves[9].name == "eRob"


def test_a_value_out_of_the_type_range_is_refused_before_the_tool_runs(igh):
    with pytest.raises(SdoError, match="value 300 does not fit uint8"):
        IghSdo().download(0, 0x2383, 0, 300, "uint8")
    assert igh.calls == []
