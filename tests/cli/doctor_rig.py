"""Run `prime doctor` against the virtual Prime with faults staged, in a private network namespace.

    python doctor_rig.py OUT STAGE[,STAGE...] [DOCTOR ARGUMENTS...]

OUT holds ``truth.yaml`` (the virtual robot's wiring and factory offsets) and ``calibration.yaml`` (what the doctor
reads); the rig writes ``prime_hardware.yaml`` there (the bundled one, its buses on the virtual Prime's), stages the
faults, runs the doctor as its own process with ``--summary OUT/report.json`` and leaves its exit status and output
in ``rc`` and ``stdout``. Stages: ``healthy``; ``no-carrier`` (the veth's peer down); ``no-cap-net-raw`` (the doctor
run under ``capsh --drop=cap_net_raw``); ``identity@N`` and ``revision@N`` (ring N presents another product code or
firmware revision); ``fault@N`` (ring N faults with 0x8500, which its history keeps); ``silent-wrist``
(left_wrist_pitch gives no feedback); ``foreign-frames`` (ARP frames reach the ring's NIC from the cable, sent on
the veth's other end, while the doctor runs);
``rated-torque`` (every eRob reports 31 N*m, as an eRob80H120I does).
"""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
from pathlib import Path

import yaml

from humanoid_prime.files import bundled
from humanoid_prime.virtual.harness import CAN_CHANNEL, CAN_INTERFACE, VirtualPrime, enter_private_netns

OTHER_PRODUCT = 0x00029253
OTHER_REVISION = 0x00000002
ARP_REQUEST = bytes.fromhex("ffffffffffff" "020000000001" "0806" "0001080006040001" "020000000001" "c0000201"
                            "000000000000" "c0000202")


def send_frames(interface: str, stop: threading.Event) -> None:
    """An ARP request on ``interface`` every 20 ms until ``stop``: a device on the cable that is no EtherCAT slave."""
    with socket.socket(socket.AF_PACKET, socket.SOCK_RAW) as raw:
        raw.bind((interface, 0))
        while not stop.wait(0.02):
            raw.send(ARP_REQUEST)


def main(argv: list[str]) -> int:
    out, stages, doctor_args = Path(argv[0]), argv[1].split(","), argv[2:]
    enter_private_netns()
    options = {"rated_torque_mnm": 31000} if "rated-torque" in stages else {}
    with VirtualPrime(truth_file=out / "truth.yaml", **options) as virtual:
        hardware = yaml.safe_load(bundled("prime_hardware.yaml").read_text())
        hardware["buses"]["ethercat"]["interface"] = virtual.master_interface
        hardware["buses"]["can"].update(interface=CAN_INTERFACE, channel=CAN_CHANNEL)
        (out / "prime_hardware.yaml").write_text(yaml.safe_dump(hardware, sort_keys=False))
        command = [sys.executable, "-m", "humanoid_prime", "doctor", "--hardware", str(out / "prime_hardware.yaml"),
                   "--calibration", str(out / "calibration.yaml"), "--summary", str(out / "report.json"),
                   *doctor_args]
        stop = threading.Event()
        sender = None
        for stage in stages:
            kind, _, position = stage.partition("@")
            if kind == "no-carrier":
                subprocess.run(["ip", "link", "set", virtual.emulator_interface, "down"], check=True)
            elif kind == "no-cap-net-raw":
                command = ["capsh", "--drop=cap_net_raw", "--", "-c", 'exec "$@"', "doctor", *command]
            elif kind == "identity":
                virtual.control.set_identity(int(position), product_code=OTHER_PRODUCT)
            elif kind == "revision":
                virtual.control.set_identity(int(position), revision=OTHER_REVISION)
            elif kind == "fault":
                virtual.control.inject_fault(int(position), 0x8500)
            elif kind == "silent-wrist":
                virtual.control.call("sito", joint="left_wrist_pitch", silent=True)
            elif kind == "foreign-frames":
                sender = threading.Thread(target=send_frames, args=(virtual.emulator_interface, stop), daemon=True)
                sender.start()
            elif kind not in ("healthy", "rated-torque"):
                raise SystemExit(f"unknown stage {stage!r}")
        try:
            proc = subprocess.run(command, capture_output=True, text=True, timeout=120)
        finally:
            stop.set()
            if sender is not None:
                sender.join()
    (out / "stdout").write_text(proc.stdout)
    (out / "stderr").write_text(proc.stderr)
    (out / "rc").write_text(str(proc.returncode))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
