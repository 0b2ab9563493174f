"""`prime bringup --emulate`: the whole robot on the virtual Prime, checked against the drives' own record."""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from doubles.process import popen
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.drivers.erob.gains import gains_to_registers
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import bundled
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.socket import request
from humanoid_prime.virtual.netns import netns_unavailable_reason

REASON = netns_unavailable_reason()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(REASON is not None, reason=f"emulated bringup: {REASON}")]

PRIME = [sys.executable, "-m", "humanoid_prime"]


def bringup(tmp_path: Path, *args: str, timeout: float = 120.0) -> dict:
    summary = tmp_path / "summary.json"
    proc = subprocess.run([*PRIME, "bringup", "--emulate", "--no-live", "--summary", str(summary),
                           "--socket", str(tmp_path / "control.sock"), *args],
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr
    return json.loads(summary.read_text())


def wait_until_up(proc: subprocess.Popen, socket: Path) -> None:
    """Until the running bringup answers on its control socket, then a second of steady running."""
    deadline = time.monotonic() + 60
    while True:
        with contextlib.suppress(PrimeError):
            if request(socket, {"op": "ping"}, timeout=0.5)["ready"]:
                break
        assert proc.poll() is None and time.monotonic() < deadline, "bringup did not come up"
        time.sleep(0.1)
    time.sleep(1.0)


@pytest.fixture(scope="module")
def switching_run(tmp_path_factory) -> dict:
    """One run visiting DAMPING and STANDBY twice each, recorded: most tests read its summary."""
    folder = tmp_path_factory.mktemp("switching")
    summary = bringup(folder, "--sequence", "DAMPING,STANDBY,DAMPING,STANDBY,DAMPING", "--dwell", "0.6",
                      "--record", str(folder / "run.mcap"))
    summary["recording"] = folder / "run.mcap"
    return summary


def test_the_run_is_recorded_tick_for_tick_with_its_modes_in_the_system_clock(switching_run):
    from rosbags.highlevel import AnyReader

    with AnyReader([switching_run["recording"]]) as reader:
        stamps, modes = [], []
        for connection, log_time, raw in reader.messages():
            if connection.topic == "/prime/joint_states":
                stamps.append(log_time)
            elif connection.topic == "/control_mode":
                modes.append(reader.deserialize(raw, connection.msgtype).data)
    record = switching_run["record"]
    # Every tick from the moment the run was up: the bring-up's first tick comes before the recorder attaches.
    ticks = switching_run["ticks"] - 1
    assert len(stamps) == record["messages"]["/prime/joint_states"] == ticks - record["dropped_ticks"]
    assert modes == switching_run["modes_visited"]
    assert abs(stamps[-1] * 1e-9 - time.time()) < 24 * 3600  # epoch stamps (the robot's clock), not monotonic


def replay(log: list[dict], position: int) -> list[tuple[int, int, int]]:
    """(gate, pos_reg, vel_reg) after every accepted write to one slave, in order."""
    gate, pos, vel = 0, None, None
    states = []
    for entry in log:
        if entry["position"] != position or not entry["applied"]:
            continue
        if entry["index"] == 0x2383:
            gate = entry["value"]
        elif (entry["index"], entry["sub"]) == (0x2382, 1):
            pos = entry["value"]
        elif (entry["index"], entry["sub"]) == (0x2381, 1):
            vel = entry["value"]
        else:
            continue
        states.append((gate, pos, vel))
    return states


def expected(mode: Mode) -> tuple[int, int]:
    kp, kd = load_controllers(tuple(yaml.safe_load(bundled("prime_hardware.yaml").read_text())["joints"]
                                    ["all_joints"])).mode_gains()[mode]
    regs = gains_to_registers(kp, kd)
    return regs.pos_reg, regs.vel_reg


def test_all_fourteen_joints_come_up_on_both_buses(switching_run):
    assert switching_run["ok"] and switching_run["problems"] == []
    end = switching_run["end"]
    assert (end["slaves_op"], end["drives_enabled"], end["drives_faulted"], end["sito_online"]) == (10, 10, [], 4)
    assert [f for f in switching_run["faults"] if f["level"] == "ERROR"] == []
    assert switching_run["fallbacks"] == []
    assert switching_run["modes_visited"] == ["ZERO_TORQUE", "DAMPING", "STANDBY", "DAMPING", "STANDBY", "DAMPING"]


def test_stages_run_in_the_documented_order(switching_run):
    names = [stage["name"] for stage in switching_run["stages"]]
    order = ["hardware configure", "joint_state_broadcaster", "zero_torque_controller", "damping_controller",
             "standby_controller", "locomotion_controller", "remote_policy_controller", "hardware activate",
             "controllers activated", "first tick", "impedance manager started"]
    assert [n for n in names if n in order] == order


def test_every_slave_holds_the_design_registers_of_each_mode(switching_run):
    damping, standby = expected(Mode.DAMPING), expected(Mode.STANDBY)
    assert standby == (515, 19) and damping == (0, 56)
    log = switching_run["emulator"]["sdo_log"]
    for position in range(10):
        pairs = [(pos, vel) for gate, pos, vel in replay(log, position) if gate == 1]
        assert damping in pairs and standby in pairs, f"ring {position}: {pairs}"
        assert pairs[-1] == damping  # the run ended in DAMPING


def test_no_intermediate_register_pair_is_stiffer_than_both_modes(switching_run):
    modes = {expected(m) for m in Mode}
    log = switching_run["emulator"]["sdo_log"]
    for position in range(10):
        pairs = [(pos, vel) for gate, pos, vel in replay(log, position)
                 if gate == 1 and pos is not None and vel is not None]
        anchors = [i for i, pair in enumerate(pairs) if pair in modes]
        for a, b in zip(anchors, anchors[1:], strict=False):
            (pa, va), (pb, vb) = pairs[a], pairs[b]
            for pos, vel in pairs[a + 1:b]:
                assert pos * vel <= max(pa * va, pb * vb), f"ring {position}: stiffer intermediate {pos, vel}"
                assert vel <= max(va, vb), f"ring {position}: more damped intermediate {pos, vel}"


def test_no_sdo_reached_a_drive_before_op(switching_run):
    for slave in switching_run["emulator"]["slaves"]:
        assert slave["mailbox_faults"] == 0, slave
        assert 0xA000 not in slave["error_history"], slave


def test_every_mode_switch_reaches_every_slave(switching_run):
    switches = [s for s in switching_run["mode_switches"] if s["mode"] in ("DAMPING", "STANDBY")]
    assert len(switches) == 5 and all(s["ok"] for s in switches)
    assert all(s["wall_seconds"] >= s["skew_seconds"] >= 0 for s in switches)  # the times are the bench's


def test_gate_is_back_to_zero_after_the_run(switching_run):
    assert switching_run["gate_reset_failures"] == []
    assert all(slave["gate"] == 0 for slave in switching_run["emulator"]["slaves"])


def test_parallel_sdo_overlaps_the_drives_mailbox_service_and_sequential_sdo_never_does(tmp_path):
    """With a drive-like 5 ms mailbox service time, as the drives saw it: parallel writes reach several slaves
    while one is still serving a request; sequential ones arrive at least one service time apart."""
    latency = 0.005
    closest = {}
    for label, extra in (("parallel", []), ("sequential", ["--sequential-sdo"])):
        run = bringup(tmp_path / label, "--sequence", "DAMPING,STANDBY", "--dwell", "0.4",
                      "--mailbox-latency", str(latency), *extra)
        times = sorted(e["time"] for e in run["emulator"]["sdo_log"])
        closest[label] = min(b - a for a, b in zip(times, times[1:], strict=False))
    assert closest["sequential"] >= latency - 1e-6 and closest["parallel"] < latency, closest


@pytest.mark.parametrize("variant, rated", [
    ((), 23.0),  # ZeroErr's EDS: gains UNSIGNED16, nominal rated torque
    (("--gain-bytes", "4"), 23.0),  # a drive that holds the gains in 32 bits (as one public host reads them)
    (("--rated-torque", "31"), 31.0),  # an eRob80H120I
])
def test_mode_switches_succeed_on_each_vendor_variant(tmp_path, variant, rated):
    """Each variant refuses an SDO of the wrong size, as a real CoE stack does, and powers up in ZeroErr's own
    PDO mapping, so a clean run proves the remap, the sizes and the rated torque read at bring-up."""
    run = bringup(tmp_path, "--sequence", "DAMPING,STANDBY,DAMPING", "--dwell", "0.4", *variant)
    assert run["ok"] and run["problems"] == [], run["problems"]
    switches = [s for s in run["mode_switches"] if s["mode"] in ("DAMPING", "STANDBY")]
    assert len(switches) == 3 and all(s["ok"] for s in switches)
    assert set(run["ethercat_bringup"]["rated_torque_nm"].values()) == {rated}
    assert not any(f["key"].endswith("/rated_torque") for f in run["faults"])
    standby = expected(Mode.STANDBY)
    log = run["emulator"]["sdo_log"]
    assert all(e["applied"] for e in log), [e for e in log if not e["applied"]]
    for position in range(10):
        assert standby in [(pos, vel) for gate, pos, vel in replay(log, position) if gate == 1]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_gate_is_zero_on_every_slave_after_a_signal(tmp_path, sig):
    summary, socket = tmp_path / "summary.json", tmp_path / "control.sock"
    proc = popen([*PRIME, "bringup", "--emulate", "--no-live", "--summary", str(summary),
                             "--socket", str(socket), "--mode", "STANDBY", "--dwell", "1000"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_until_up(proc, socket)
        proc.send_signal(sig)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, proc.stderr.read()
    data = json.loads(summary.read_text())
    assert any(s["mode"] == "STANDBY" for s in data["mode_switches"])  # the gate had been armed
    assert [slave["gate"] for slave in data["emulator"]["slaves"]] == [0] * 10


def test_sync0_that_differs_from_the_loop_is_refused_before_the_bus(tmp_path):
    proc = subprocess.run([*PRIME, "bringup", "--sync0-period", "0.001", "--interface", "does-not-exist0"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1
    assert "sync0_period 1 ms differs from the loop period 20 ms" in proc.stderr
    assert "4616" in proc.stderr


def _hardware_with_efficiency(tmp_path: Path, efficiency: float) -> Path:
    data = yaml.safe_load(bundled("prime_hardware.yaml").read_text())
    data["torque_efficiency"] = efficiency
    path = tmp_path / "prime_hardware.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(("efficiency", "ratio"), [(1.0, 0.7), (0.7, 1.0)])
def test_load_test_reports_realised_stiffness(tmp_path, efficiency, ratio):
    hardware = _hardware_with_efficiency(tmp_path, efficiency)
    run = bringup(tmp_path, "--hardware", str(hardware), "--load-test", "left_wrist_yaw", timeout=180)
    (row,) = run["load_test"]
    assert row["kp_nominal"] == 20.0
    assert row["ratio"] == pytest.approx(ratio, abs=0.05)


def test_ctrl_c_at_a_terminal_still_resets_every_gate(tmp_path):
    """A terminal's Ctrl-C signals the whole process group; the virtual Prime must outlive the master's
    teardown so the gate reset reaches every drive."""
    import os

    summary, socket = tmp_path / "summary.json", tmp_path / "control.sock"
    proc = popen([*PRIME, "bringup", "--emulate", "--no-live", "--summary", str(summary),
                             "--socket", str(socket), "--mode", "DAMPING"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        wait_until_up(proc, socket)
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, proc.stderr.read()
    data = json.loads(summary.read_text())
    assert data["gate_reset_failures"] == []
    assert [slave["gate"] for slave in data["emulator"]["slaves"]] == [0] * 10
