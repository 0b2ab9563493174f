"""`prime doctor` against the virtual Prime in its network namespace: healthy, it exits 0 with every line a pass or
an honest warn; each fault staged there (doctor_rig.py) is found, with its fix."""

from __future__ import annotations

import json
import random
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from humanoid_prime.cli import main
from humanoid_prime.config.calibration import Calibration, JointCalibration, save_calibration
from humanoid_prime.virtual.netns import netns_unavailable_reason

REASON = netns_unavailable_reason()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(REASON is not None, reason=f"no virtual Prime: {REASON}")]
RIG = Path(__file__).with_name("doctor_rig.py")
LINE = re.compile(r"^  (pass|warn|fail)  (\S+)\s+(.*)$")


@dataclass
class Run:
    rc: int
    stdout: str
    report: dict

    def check(self, check_id: str) -> dict:
        return next(c for c in self.report["checks"] if c["id"] == check_id)

    def verdicts(self) -> dict[str, str]:
        return {c["id"]: c["verdict"] for c in self.report["checks"]}


@pytest.fixture(scope="module")
def configs(robot, tmp_path_factory) -> dict[str, Path]:
    """The virtual robot's wiring (factory offsets, two joints backwards), the calibration that matches it, and the
    identity a robot that was never calibrated has."""
    folder = tmp_path_factory.mktemp("doctor-configs")
    rng = random.Random(44)
    truth = Calibration({j: JointCalibration(-1 if j in ("left_shoulder_roll", "right_wrist_yaw") else 1,
                                             round(rng.uniform(-0.5, 0.5), 5)) for j in robot.names})
    save_calibration(folder / "truth.yaml", truth, robot.hardware)
    save_calibration(folder / "identity.yaml", Calibration({j: JointCalibration() for j in robot.names}),
                     robot.hardware)
    return {"truth": folder / "truth.yaml", "identity": folder / "identity.yaml"}


def rig(folder: Path, configs: dict[str, Path], stages: str, *doctor_args: str, calibration: str = "truth") -> Run:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "truth.yaml").write_bytes(configs["truth"].read_bytes())
    (folder / "calibration.yaml").write_bytes(configs[calibration].read_bytes())
    proc = subprocess.run([sys.executable, str(RIG), str(folder), stages, *doctor_args], capture_output=True,
                          text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr
    stdout = (folder / "stdout").read_text()
    assert (folder / "report.json").exists(), (folder / "stderr").read_text()
    return Run(int((folder / "rc").read_text()), stdout, json.loads((folder / "report.json").read_text()))


@pytest.fixture(scope="module")
def healthy(configs, tmp_path_factory) -> Run:
    return rig(tmp_path_factory.mktemp("healthy"), configs, "healthy", "--backends", "ec,can")


@pytest.fixture(scope="module")
def ring_faults(configs, tmp_path_factory) -> Run:
    """Another device at ring 3, another firmware at ring 6, a fault at ring 2, frames from a device on the ring's
    cable that is no EtherCAT slave, and every drive reporting another model's rated torque."""
    return rig(tmp_path_factory.mktemp("ring"), configs, "identity@3,revision@6,fault@2,foreign-frames,rated-torque",
               "--backends", "ec")


@pytest.fixture(scope="module")
def operated(configs, tmp_path_factory) -> Run:
    """--op on a robot never calibrated, with one wrist silent."""
    return rig(tmp_path_factory.mktemp("op"), configs, "silent-wrist", "--op", calibration="identity")


# ------------------------------------------------------------------------------------------------------ healthy
def test_the_healthy_virtual_prime_exits_0_with_every_line_a_pass_or_a_warn(healthy):
    assert healthy.rc == 0, healthy.stdout
    assert healthy.report["ok"] and healthy.report["failed"] == 0
    assert {v for k, v in healthy.verdicts().items() if k.startswith("ethercat.")} == {"pass"}
    assert healthy.check("robot.calibration")["verdict"] == "pass"


def test_what_the_virtual_prime_cannot_show_is_not_checked_and_says_why(healthy):
    unchecked = {c["id"]: c["found"] for c in healthy.report["checks"] if not c["ran"]}
    assert set(unchecked) >= {"can.link", "can.wrist.left_wrist_roll", "can.wrist.left_wrist_pitch",
                              "can.wrist.right_wrist_roll", "can.wrist.right_wrist_pitch"}
    assert "not a SocketCAN link" in unchecked["can.link"]
    assert "a Sito sends only once enabled" in unchecked["can.wrist.left_wrist_roll"]
    assert all(found.startswith("not checked: ") for found in unchecked.values())


def test_the_lines_and_the_json_hold_the_same_checks_with_the_same_verdicts(healthy):
    shown = [(m[2], m[1]) for m in (LINE.match(line) for line in healthy.stdout.splitlines()) if m]
    assert shown == [(c["name"], c["verdict"]) for c in healthy.report["checks"]]
    assert healthy.stdout.splitlines()[-1].startswith(f"0 failed, {healthy.report['warned']} warned")


# ---------------------------------------------------------------------------------------------- staged faults
def test_another_device_at_a_ring_position_is_found_with_the_file_to_fix(ring_faults):
    check = ring_faults.check("ethercat.identity")
    assert check["verdict"] == "fail" and ring_faults.rc == 1
    assert "ring 3: expected left_elbow_pitch (eRob vendor 0x5A65726F product 0x00029252), found" in check["found"]
    assert "product 0x00029253" in check["found"]
    assert check["fix"].startswith("fix the cabling order, or joints.erob_slaves in ")


def test_a_firmware_revision_prime_is_not_tested_with_is_found(ring_faults):
    check = ring_faults.check("ethercat.revision")
    assert check["verdict"] == "warn"
    assert "ring 6 (right_shoulder_roll): revision 0x00000002, not one Prime is tested with" in check["found"]
    assert "ZeroErr's tool" in check["fix"]


def test_a_drive_with_an_error_in_its_history_is_found_with_how_to_read_and_clear_it(ring_faults):
    history, errors = ring_faults.check("ethercat.history"), ring_faults.check("ethercat.errors")
    assert history["verdict"] == "warn" and "ring 2 (left_shoulder_yaw) 0x8500" in history["found"]
    assert "prime ec sdo write 2 0x1003:0 0" in history["fix"]
    assert errors["verdict"] == "fail" and "ring 2 (left_shoulder_yaw) error 0x8500" in errors["found"]


def test_a_rated_torque_of_another_model_is_found(ring_faults):
    check = ring_faults.check("ethercat.rated_torque")
    assert check["verdict"] == "fail"
    assert "ring 9 (right_wrist_yaw): reads 31 N*m, what an eRob80H120I reports" in check["found"]
    assert check["found"].count("eRob80H120I") == 1  # one finding, once, for the nine drives that read it


def test_a_foreign_frame_on_the_ring_s_nic_is_found_with_where_to_look(ring_faults):
    check = ring_faults.check("host.nic.traffic")
    assert check["verdict"] == "fail" and re.search(r"\d+ ARP received", check["found"])
    assert check["fix"].startswith("find what else is on ecm")
    assert ring_faults.check("host.nic.users")["verdict"] == "pass"  # no program of this host sent them


def test_a_silent_wrist_is_found_by_the_limp_probe_and_the_others_answer(operated):
    assert operated.check("can.wrist.left_wrist_pitch")["verdict"] == "fail"
    assert "id 23 is silent" in operated.check("can.wrist.left_wrist_pitch")["found"]
    assert {operated.check(f"can.wrist.{j}")["verdict"] for j in ("left_wrist_roll", "right_wrist_roll",
                                                                   "right_wrist_pitch")} == {"pass"}


def test_op_takes_the_ring_to_op_and_back_with_the_drives_out_of_fault(operated):
    check = operated.check("ethercat.op")
    assert check["verdict"] == "pass" and check["found"].startswith("every slave in OP in ")


def test_an_identity_calibration_is_found_with_how_to_calibrate(operated):
    check = operated.check("robot.calibration")
    assert check["verdict"] == "fail" and "every homing_offset is 0" in check["found"]
    assert check["fix"].startswith("prime calibrate --auto")


def test_no_carrier_is_found_and_the_ring_is_not_checked(configs, tmp_path):
    run = rig(tmp_path / "no-carrier", configs, "no-carrier", "--backends", "ec")
    assert run.rc == 1
    carrier = run.check("host.nic.carrier")
    assert carrier["verdict"] == "fail" and carrier["found"].startswith("no carrier on ecm")
    assert "first drive's IN port" in carrier["fix"]
    assert {c["found"] for c in run.report["checks"] if c["group"] == "ethercat"} == {
        f"not checked: {run.report['context']['ethercat_interface']} is not usable"}


def test_a_missing_cap_net_raw_is_found_and_the_ring_is_not_checked(configs, tmp_path):
    run = rig(tmp_path / "no-cap", configs, "no-cap-net-raw", "--backends", "ec")
    assert run.rc == 1
    check = run.check("host.cap_net_raw")
    assert check["verdict"] == "fail" and check["found"].startswith("no CAP_NET_RAW: SOEM cannot open a raw socket")
    assert "setcap cap_net_raw" in check["fix"]
    assert run.check("ethercat.scan")["found"] == "not checked: no CAP_NET_RAW"


# ------------------------------------------------------------------------------------------ without the robot
def test_without_the_robot_every_bus_check_says_why_it_could_not_run(robot, tmp_path, capsys):
    hardware = tmp_path / "prime_hardware.yaml"
    text = robot.hardware.path.read_text().replace("channel: can2", "channel: prime-no-can0")
    hardware.write_text(text)
    assert main(["doctor", "--hardware", str(hardware), "--interface", "prime-no-nic0", "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    unchecked = {c["id"]: c["found"] for c in report["checks"] if not c["ran"]}
    assert report["failed"] >= 2  # the NIC and the CAN link
    assert {k for k in unchecked if k.startswith("ethercat.")} == {
        f"ethercat.{name}" for name in ("scan", "identity", "revision", "al_status", "dc", "mailbox", "rated_torque",
                                        "errors", "history")}
    assert unchecked["ethercat.scan"] == "not checked: prime-no-nic0 is not usable"
    assert unchecked["can.bitrate"] == "not checked: no interface 'prime-no-can0'"
