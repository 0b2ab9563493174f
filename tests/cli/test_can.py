"""``prime can monitor`` and ``prime can discover`` against emulated wrists on a virtual bus."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator

import can
import pytest

from doubles.sito import SITO_IDS, wait_until
from humanoid_prime.cli import main
from humanoid_prime.cli.can import describe
from humanoid_prime.drivers.sito.protocol import (
    SITO_MODELS,
    Command,
    Disable,
    Enable,
    Feedback1,
    Feedback2,
    FrameType,
    Gains,
    UndecodedFeedback,
    pack_frame,
)
from humanoid_prime.virtual.sito import SitoEmulator

TA40_50 = SITO_MODELS["TA40-50"]
JOINTS = {22: "left_wrist_roll"}


def message(can_id: int, frame) -> can.Message:
    ident, data = pack_frame(can_id, frame)
    return can.Message(arbitration_id=ident, is_extended_id=True, data=data)


@pytest.fixture
def emulated(robot) -> Iterator[tuple[SitoEmulator, str]]:
    channel = f"sito-cli-{uuid.uuid4().hex}"
    bus = can.Bus(interface="virtual", channel=channel)
    emulator = SitoEmulator.for_robot(robot, bus)
    emulator.start()
    yield emulator, channel
    emulator.stop()
    bus.shutdown()


def enable_all(emulator: SitoEmulator) -> None:
    for motor in emulator.motors.values():
        motor.receive(FrameType.ENABLE, pack_frame(motor.can_id, Enable(0x09, (10, 10, 0)))[1])


def test_describe_command():
    text = describe(message(22, Command(100, 5215, 10430)), TA40_50, JOINTS)
    assert text == ("id  22 left_wrist_roll    command pos 10430 (+1.0000 rad) vel 5215 (+0.5000 rad/s) "
                    "ff 100 mA (+0.459 Nm)")


def test_describe_gains_in_si():
    text = describe(message(22, Gains(1.0, 2.0)), TA40_50, JOINTS)
    assert "Kp 1 (688.580 Nm/rad) Kd 2 (2.250 Nm·s/rad)" in text


def test_describe_enable_and_disable():
    assert "enable mode 0x09 (MIT), feedback every 20/20/0 ms" in describe(
        message(22, Enable(0x09, (20, 20, 0))), TA40_50, JOINTS)
    assert describe(message(22, Disable()), TA40_50, JOINTS).endswith("disable (reset)")


def test_describe_feedback():
    assert "current(4-5) 100 mA (+0.459 Nm) current(2-3) 0 mA (+0.000 Nm) vel -5215 (-0.5000 rad/s)" in describe(
        message(22, Feedback1(240, 0, 100, -5215)), TA40_50, JOINTS)
    assert "output 10430 (+1.0000 rad)" in describe(message(22, Feedback2(531930, 10430)), TA40_50, JOINTS)


def test_describe_shows_both_readings_of_the_phase_current():
    # the peer's newest driver reads bytes 2-3, its older one and ours bytes 4-5: a real motor settles it
    text = describe(message(22, Feedback1(240, -200, 100, 0)), TA40_50, JOINTS)
    assert "current(4-5) 100 mA (+0.459 Nm) current(2-3) -200 mA (-0.918 Nm)" in text


def test_describe_undocumented_feedback():
    text = describe(message(22, UndecodedFeedback(0xB3, bytes(range(8)))), TA40_50, JOINTS)
    assert text.endswith("feedback 0xB3 (layout undocumented, ignored by the driver): 00 01 02 03 04 05 06 07")


def test_describe_flags_a_protocol_breaking_frame():
    msg = can.Message(arbitration_id=0x050616B2, is_extended_id=True, data=bytes(5))
    assert "INVALID type 0xB2 (5 data bytes" in describe(msg, TA40_50, JOINTS)


def test_describe_unconfigured_and_foreign_ids():
    assert "(not configured)" in describe(message(40, Disable()), TA40_50, JOINTS)
    assert describe(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01"), TA40_50, JOINTS) == (
        "foreign id 0x123 dlc 1: 01")


def test_monitor_decodes_live_feedback(emulated, capsys, tmp_path):
    emulator, channel = emulated
    enable_all(emulator)
    assert main(["can", "monitor", "--interface", "virtual", "--channel", channel, "--count", "8",
                 "--summary", str(tmp_path / "s.json")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 8
    assert json.loads((tmp_path / "s.json").read_text())["frames"] == 8
    assert any("left_wrist_roll" in line and "feedback-2" in line for line in lines)


def test_discover_lists_the_streaming_ids_without_sending(emulated, capsys):
    emulator, channel = emulated
    enable_all(emulator)
    assert main(["can", "discover", "--interface", "virtual", "--channel", channel, "--seconds", "0.2"]) == 0
    out = capsys.readouterr().out
    assert all(f"CAN id {i:3d}" in out for i in SITO_IDS)
    assert emulator.frames_received == 0


def test_discover_without_traffic_suggests_probe(emulated, capsys):
    _, channel = emulated
    main(["can", "discover", "--interface", "virtual", "--channel", channel, "--seconds", "0.1"])
    assert "--probe" in capsys.readouterr().out


def test_discover_probe_enables_with_zero_gains_then_disables(emulated, capsys):
    emulator, channel = emulated
    code = main(["can", "discover", "--interface", "virtual", "--channel", channel, "--seconds", "0.2",
                 "--probe", "--json"])
    assert code == 0
    assert '"can_id": 39' in capsys.readouterr().out
    for motor in emulator.motors.values():
        assert motor.received[FrameType.GAINS] == 1 and motor.received[FrameType.ENABLE] == 1
    wait_until(lambda: all(m.disables == 1 and not m.enabled for m in emulator.motors.values()), "the disables")


def test_discover_probe_fails_when_a_probed_id_is_silent(emulated, capsys):
    emulator, channel = emulated
    emulator.motors[23].silent = True
    assert main(["can", "discover", "--interface", "virtual", "--channel", channel, "--seconds", "0.2",
                 "--probe", "--ids", "22-23"]) == 1
    assert "not heard: 23 (left_wrist_pitch)" in capsys.readouterr().out


def test_discover_counts_only_frames_the_protocol_accepts_as_a_wrist_s_feedback(capsys):
    # 0xB2 on wrist 22 in 3 bytes and in a 64-byte CAN FD frame (monitor calls both INVALID); wrist 23 is healthy
    channel = f"sito-cli-{uuid.uuid4().hex}"
    ident = 0x050616B2
    frames = [can.Message(arbitration_id=ident, is_extended_id=True, data=bytes(3)),
              can.Message(arbitration_id=ident, is_extended_id=True, is_fd=True, data=bytes(64)),
              message(23, Feedback2(0, 10430))]
    assert all("INVALID" in describe(f, TA40_50, JOINTS) for f in frames[:2])
    stop = threading.Event()

    def stream() -> None:
        with can.Bus(interface="virtual", channel=channel) as bus:
            while not stop.wait(0.005):
                for frame in frames:
                    bus.send(frame)

    sender = threading.Thread(target=stream)
    sender.start()
    try:
        code = main(["can", "discover", "--interface", "virtual", "--channel", channel, "--seconds", "1",
                     "--json"])
    finally:
        stop.set()
        sender.join()
    result = json.loads(capsys.readouterr().out)
    assert code == 1
    assert [entry["can_id"] for entry in result["heard"]] == [23]
    assert [(e["can_id"], e["joint"]) for e in result["invalid"]] == [(22, "left_wrist_roll")]
    assert {"can_id": 22, "joint": "left_wrist_roll"} in result["not_heard"]


def test_bad_ids_exit_with_one_line(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["can", "discover", "--probe", "--ids", "22,abc"])
    assert exit_info.value.code == 2
    assert "not a list of CAN ids" in capsys.readouterr().err


def test_missing_interface_is_one_line_and_exit_1(capsys):
    assert main(["can", "monitor", "--channel", "can_missing0", "--seconds", "0.1"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ip link set can_missing0 up" in err[0]


@pytest.mark.parametrize("action", ["monitor", "discover", "emulate"])
def test_a_channel_that_cannot_be_opened_is_one_line_and_nothing_after_it(action):
    # python-can's "UdpMulticastBus was not properly shut down" used to follow, from the half-opened bus
    proc = subprocess.run([sys.executable, "-m", "humanoid_prime", "can", action, "--interface", "udp_multicast",
                           "--channel", "notanip", "--seconds", "0.1"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.startswith("prime can: cannot open CAN channel 'notanip' (udp_multicast)")
    assert proc.stderr.count("\n") == 1, proc.stderr


def test_emulate_answers_as_the_wrists(channel, tmp_path):
    host = can.Bus(interface="virtual", channel=channel)
    codes: list[int] = []
    summary = tmp_path / "s.json"
    worker = threading.Thread(target=lambda: codes.append(
        main(["can", "emulate", "--interface", "virtual", "--channel", channel, "--seconds", "0.5",
              "--summary", str(summary)])))
    worker.start()
    try:
        feedback = None
        deadline = time.monotonic() + 5.0
        while feedback is None and time.monotonic() < deadline:  # until the emulator has opened the bus
            host.send(message(22, Enable(0x09, (10, 10, 0))), timeout=0.0)
            msg = host.recv(0.05)
            if msg is not None and msg.arbitration_id & 0xFF in (0xB1, 0xB2):
                feedback = msg
        worker.join()
        assert codes == [0]
        assert feedback is not None and (feedback.arbitration_id >> 8) & 0xFF == 22
        figures = json.loads(summary.read_text())
        assert figures["ids"] == [22, 23, 38, 39] and figures["frames_received"] >= 1
    finally:
        worker.join()
        host.shutdown()


def test_emulate_refuses_socketcan(capsys):
    assert main(["can", "emulate", "--seconds", "0.1"]) == 1
    assert "refusing to emulate wrists on SocketCAN channel 'can2'" in capsys.readouterr().err
