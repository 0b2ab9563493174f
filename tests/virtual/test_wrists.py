"""The virtual Prime's wrists in a process of their own: the child parses the host's frames and streams
feedback, the parent applies each firmware's MIT law to the MuJoCo world at every physics step."""

from __future__ import annotations

import random
from collections.abc import Iterator

import can
import pytest

from doubles.sito import wait_until
from humanoid_prime.drivers.sito.protocol import (
    MODE_MIT,
    Command,
    Enable,
    Feedback2,
    FrameType,
    Gains,
    kd_to_firmware,
    kp_to_firmware,
    pack_frame,
    parse_frame,
    position_to_counts,
    split_arbitration_id,
)
from humanoid_prime.errors import PrimeError
from humanoid_prime.virtual.plant import PrimeWorld, truth_calibration
from humanoid_prime.virtual.sito import sito_model
from humanoid_prime.virtual.wrists import WristProcess

pytest.importorskip("msgpack", reason="python-can's udp_multicast interface needs msgpack")
JOINT = "left_wrist_roll"
MODEL = sito_model("TA40-50")


@pytest.fixture
def bus_options() -> dict[str, object]:
    group = f"239.{random.randint(1, 254)}.{random.randint(1, 254)}.{random.randint(1, 254)}"
    return {"interface": "udp_multicast", "channel": group, "port": random.randint(20000, 60000)}


@pytest.fixture
def prime(robot, bus_options) -> Iterator[tuple[PrimeWorld, WristProcess, can.BusABC]]:
    world = PrimeWorld(robot, truth_calibration(robot), physics_dt=0.001)
    wrists = WristProcess(robot, world, bus=bus_options, rate_hz=1000.0)
    world.attach(wrists.step)
    wrists.start()
    host = can.Bus(**bus_options)
    try:
        yield world, wrists, host
    finally:
        host.shutdown()
        wrists.close()


def send(host: can.BusABC, can_id: int, frame: object) -> None:
    arbitration, data = pack_frame(can_id, frame)
    host.send(can.Message(arbitration_id=arbitration, is_extended_id=True, data=data))


def feedback_position(host: can.BusABC, can_id: int) -> float:
    """The output position of the next 0xB2 frame from ``can_id`` (rad)."""
    while True:
        message = host.recv(5.0)
        assert message is not None, "no feedback within 5 s"
        if split_arbitration_id(message.arbitration_id) == (can_id, FrameType.FEEDBACK2):
            _, frame = parse_frame(message.arbitration_id, message.data)
            assert isinstance(frame, Feedback2)
            return frame.output_position_counts / position_to_counts(1.0)


def test_the_parent_applies_the_law_the_child_received_and_the_feedback_reports_the_world(robot, prime):
    world, wrists, host = prime
    can_id = robot.hardware.mit_joints[JOINT]
    k = robot.hardware.sito_joints.index(JOINT)
    send(host, can_id, Enable(MODE_MIT, (1, 1, 0)))
    send(host, can_id, Gains(kp_to_firmware(6.0, MODEL), kd_to_firmware(0.3, MODEL)))
    send(host, can_id, Command(0, 0, position_to_counts(0.4)))
    wait_until(lambda: wrists.shared.law[k].tolist() == pytest.approx([1.0, 0.4, 0.0, 6.0, 0.3, 0.0], abs=1e-4),
               "the child's published law")
    assert wrists.shared.law[[i for i in range(4) if i != k]].tolist() == [[0.0] * 6] * 3  # the others limp
    for _ in range(1500):  # 1.5 s of physics, in this thread
        world.advance(0.001)
    q = float(wrists.view.q[k])
    assert q == pytest.approx(0.4, abs=0.05)  # held by 6 Nm/rad against the hand's weight
    wait_until(lambda: abs(feedback_position(host, can_id) - q) < 1e-4, "feedback of the world's position")


def test_faults_reach_the_child_and_a_silent_wrist_sends_nothing_while_the_others_go_on(robot, prime):
    _world, wrists, host = prime
    silent, other = (robot.hardware.mit_joints[j] for j in robot.hardware.sito_joints[:2])
    for can_id in (silent, other):
        send(host, can_id, Enable(MODE_MIT, (1, 1, 0)))
    feedback_position(host, silent)
    assert wrists.configure(silent, silent=True, drop_fraction=0.25) == {
        "can_id": silent, "silent": True, "drop_fraction": 0.25, "garbage": False}
    while host.recv(0.0) is not None:  # what was sent before the child took the fault
        pass
    heard: dict[int, int] = {silent: 0, other: 0}
    while heard[other] < 50:
        message = host.recv(5.0)
        assert message is not None, "the other wrist fell silent too"
        split = split_arbitration_id(message.arbitration_id)
        if split is not None and split[1] in (FrameType.FEEDBACK1, FrameType.FEEDBACK2) and split[0] in heard:
            heard[split[0]] += 1
    assert heard[silent] == 0
    assert wrists.configure(silent, silent=False)["silent"] is False
    feedback_position(host, silent)


def test_a_fault_the_wrists_do_not_have_or_a_motor_they_do_not_have_is_refused(robot, prime):
    _world, wrists, _host = prime
    with pytest.raises(TypeError, match="unknown Sito fault 'stuck'"):
        wrists.configure(robot.hardware.mit_joints[JOINT], stuck=True)
    with pytest.raises(KeyError, match="no emulated Sito at CAN id 99"):
        wrists.configure(99, silent=True)


def test_the_child_stops_when_closed_and_reports_its_exit(prime):
    _world, wrists, _host = prime
    process = wrists._process
    assert wrists.close() == 0
    assert not process.is_alive()
    assert wrists.close() is None


def test_a_bus_the_child_cannot_open_is_one_line_and_no_child_is_left(robot):
    world = PrimeWorld(robot, truth_calibration(robot), physics_dt=0.001)
    wrists = WristProcess(robot, world, bus={"interface": "no_such_interface", "channel": "x"}, rate_hz=1000.0)
    with pytest.raises(PrimeError, match=r"cannot open the Sito bus no_such_interface:x: .*no_such_interface"):
        wrists.start()
    assert wrists._process is None


def test_a_fault_for_wrists_whose_process_is_gone_is_one_error_not_a_crash(robot, prime):
    _world, wrists, _host = prime
    wrists._process.kill()
    wrists._process.join(5.0)
    with pytest.raises(PrimeError, match="the emulated Sito wrists' process is gone"):
        wrists.configure(robot.hardware.mit_joints[JOINT], silent=True)
