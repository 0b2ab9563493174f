"""``prime emulate ec``: runs a ring for a master, refuses the robot's NIC and bad options in one line."""

from __future__ import annotations

import pytest

from humanoid_prime.cli import main
from humanoid_prime.virtual.netns import netns_unavailable_reason

_REASON = netns_unavailable_reason()


@pytest.mark.netns
@pytest.mark.skipif(_REASON is not None, reason=_REASON or "")
def test_master_command_runs_against_the_master_end_and_its_exit_status_is_returned(capsys):
    script = 'test "$PRIME_EC_INTERFACE" = "{iface}" && test -e "/sys/class/net/{iface}" && test -S "$PRIME_EC_CONTROL"'
    assert main(["emulate", "ec", "--veth", "--slaves", "2", "--", "sh", "-c", script + " && exit 7"]) == 7
    out, err = capsys.readouterr()
    assert "master interface: ecm" in err and out == ""  # stdout is the master command's alone


@pytest.mark.netns
@pytest.mark.skipif(_REASON is not None, reason=_REASON or "")
def test_a_json_master_command_leaves_valid_json_on_stdout():
    import json
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "humanoid_prime", "emulate", "ec", "--veth", "--", sys.executable,
                           "-m", "humanoid_prime", "ec", "scan", "--interface", "{iface}", "--json"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert len(json.loads(proc.stdout)["slaves"]) == 10


def test_the_robots_ethercat_nic_is_refused(capsys):
    assert main(["emulate", "ec", "--interface", "eth0"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert "refusing to emulate on eth0" in err


def test_a_nic_that_does_not_exist_is_one_line(capsys):
    assert main(["emulate", "ec", "--interface", "nonexistent0"]) == 1
    assert capsys.readouterr().err == ("prime emulate: no network interface 'nonexistent0' to serve (--interface); "
                                       "list them with `ip link`, or use --veth\n")


def test_an_option_out_of_range_is_one_line(capsys):
    assert main(["emulate", "ec", "--veth", "--mailbox-size", "8"]) == 1
    assert capsys.readouterr().err.strip() == "prime emulate: mailbox_size must be 32..1024 bytes, got 8"
