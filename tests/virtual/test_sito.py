"""The emulated Sito behaves as the firmware is documented to (DESIGN §2)."""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator

import can
import pytest

from humanoid_prime.config.calibration import Calibration, JointCalibration
from humanoid_prime.drivers.sito.bus import CAN_ERR_BUSOFF
from humanoid_prime.drivers.sito.protocol import (
    COUNTS_PER_RAD,
    SITO_MODELS,
    Command,
    Disable,
    Enable,
    Frame,
    Gains,
    InvalidFrame,
    kd_to_firmware,
    kp_to_firmware,
    pack_frame,
    parse_frame,
    position_to_counts,
    torque_to_current_mA,
    velocity_to_counts,
)
from humanoid_prime.virtual.plant import InertiaPlant, PrimeWorld, truth_calibration
from humanoid_prime.virtual.sito import TX_QUEUE_LENGTH, SitoEmulator, SitoMotor

TA40_50 = SITO_MODELS["TA40-50"]
CAN_ID = 22


class Bench:
    """One emulated motor and a host end on a private virtual channel."""

    def __init__(self, plant: InertiaPlant, **emulator_options: object) -> None:
        channel = f"sito-emu-{uuid.uuid4().hex}"
        self.motor_bus = can.Bus(interface="virtual", channel=channel)
        self.host = can.Bus(interface="virtual", channel=channel)
        self.plant = plant
        self.motor = SitoMotor(CAN_ID, plant)
        self.emulator = SitoEmulator(self.motor_bus, [self.motor], **emulator_options)

    def send(self, *frames: Frame) -> None:
        for frame in frames:
            ident, data = pack_frame(CAN_ID, frame)
            self.host.send(can.Message(arbitration_id=ident, is_extended_id=True, data=data), timeout=0.0)

    def received(self) -> list[can.Message]:
        frames = []
        while (msg := self.host.recv(0.0)) is not None:
            frames.append(msg)
        return frames

    def feedback(self) -> list[tuple[int, object]]:
        return [parse_frame(m.arbitration_id, m.data)[1] for m in self.received()]

    def close(self) -> None:
        self.emulator.stop()
        self.motor_bus.shutdown()
        self.host.shutdown()


@pytest.fixture
def bench() -> Iterator[Bench]:
    bench = Bench(InertiaPlant.wrists(1))
    yield bench
    bench.close()


def gains(kp: float, kd: float) -> Gains:
    return Gains(kp_to_firmware(kp, TA40_50), kd_to_firmware(kd, TA40_50))


def mit_enable(fb1: int = 20, fb2: int = 20) -> Enable:
    return Enable(0x09, (fb1, fb2, 0))


def test_enable_selects_mit_with_the_requested_intervals(bench):
    bench.send(mit_enable(20, 10))
    bench.emulator.step(0.001)
    assert bench.motor.enabled
    assert bench.motor.feedback_ms == (20, 10, 0)


def test_gains_frame_sets_the_realised_stiffness_and_damping(bench):
    bench.send(gains(20.0, 2.0))
    bench.emulator.step(0.001)
    assert bench.motor.kp == pytest.approx(20.0, rel=1e-6)
    assert bench.motor.kd == pytest.approx(2.0, rel=1e-6)


def test_mit_law_realises_the_commanded_kp_kd_and_feed_forward(bench):
    bench.plant.q[0], bench.plant.qd[0] = 0.1, 0.5
    bench.send(gains(20.0, 2.0), mit_enable(),
               Command(torque_to_current_mA(0.459, TA40_50)[0], 0, position_to_counts(0.3)))
    bench.emulator.process_pending()
    target = position_to_counts(0.3) / COUNTS_PER_RAD
    assert bench.motor.control() == pytest.approx(20.0 * (target - 0.1) + 2.0 * (0.0 - 0.5) + 0.459, rel=1e-6)


def test_torque_saturates_at_4_8_nm(bench):
    bench.send(gains(200.0, 0.0), mit_enable(), Command(0, 0, position_to_counts(1.0)))
    bench.emulator.process_pending()
    assert bench.motor.control() == 4.8


def test_without_gains_an_enabled_motor_is_limp(bench):
    bench.send(mit_enable(), Command(0, 0, position_to_counts(1.0)))
    bench.plant.external[0] = -0.1
    bench.emulator.step(0.2)
    assert bench.motor.torque == 0.0
    assert bench.plant.q[0] < -0.05


def test_feedback_streams_at_the_requested_intervals(bench):
    bench.send(mit_enable(20, 10))
    bench.emulator.step(0.1)
    kinds = [type(f).__name__ for f in bench.feedback()]
    assert (kinds.count("Feedback1"), kinds.count("Feedback2")) == (5, 10)


def test_no_feedback_before_enable(bench):
    bench.send(gains(20.0, 2.0))
    bench.emulator.step(0.1)
    assert bench.received() == []


def test_feedback_reports_output_position_velocity_and_current(bench):
    bench.plant.q[0], bench.plant.qd[0] = 0.25, 0.0
    bench.send(gains(0.0, 0.0), mit_enable(), Command(100, 0, 0))
    bench.emulator.step(0.001)
    fb1, fb2 = bench.feedback()[:2]
    assert fb1.phase_current_mA == 100
    assert fb1.velocity_counts == velocity_to_counts(bench.plant.qd[0])[0]
    assert fb2.output_position_counts == position_to_counts(bench.plant.q[0])


def test_disable_makes_the_motor_limp_and_silent(bench):
    bench.send(gains(20.0, 2.0), mit_enable(), Command(0, 0, position_to_counts(0.5)))
    bench.emulator.step(0.05)
    bench.send(Disable())
    bench.emulator.step(0.001)
    bench.received()
    bench.emulator.step(0.1)
    assert (bench.motor.enabled, bench.motor.disables, bench.motor.kp) == (False, 1, 0.0)
    assert bench.motor.control() == 0.0
    assert bench.received() == []


def test_enable_holds_the_current_position_until_the_first_command(bench):
    bench.plant.q[0] = 0.4
    bench.send(gains(20.0, 2.0), mit_enable())
    bench.emulator.step(0.001)
    assert bench.motor.position_counts == position_to_counts(0.4)


def test_a_protocol_breaking_frame_is_counted_and_ignored(bench):
    bench.host.send(can.Message(arbitration_id=0x05061609, is_extended_id=True, data=bytes(5)), timeout=0.0)
    bench.emulator.step(0.001)
    assert (bench.motor.invalid_received, bench.motor.position_counts) == (1, 0)


def test_silent_motor_obeys_but_sends_nothing(bench):
    bench.motor.silent = True
    bench.send(gains(20.0, 2.0), mit_enable(), Command(0, 0, position_to_counts(0.2)))
    bench.emulator.step(1.0)
    assert bench.received() == []
    assert bench.plant.q[0] == pytest.approx(0.2, abs=1e-3)


def test_late_feedback_comes_that_much_later_every_frame_of_it(bench):
    bench.send(mit_enable(10, 10))
    bench.emulator.step(0.001)
    bench.received()
    bench.motor.late_s = 0.030
    bench.emulator.step(0.029)
    assert bench.received() == []  # measured, not sent yet
    bench.emulator.step(0.031)
    kinds = [type(f).__name__ for f in bench.feedback()]
    assert (kinds.count("Feedback1"), kinds.count("Feedback2")) == (3, 3)
    bench.motor.late_s = 0.0
    bench.emulator.step(0.1)
    assert len(bench.received()) == 6 + 20 and bench.motor.late_sent == 12  # the rest held back, then on time


def test_dropping_half_the_frames_loses_about_half_the_feedback(bench):
    bench.send(mit_enable(1, 1))
    bench.emulator.step(0.001)
    bench.received()
    bench.motor.drop_fraction = 0.5
    bench.emulator.step(1.0)
    assert 800 < len(bench.received()) < 1200  # of 2000 due


def test_garbage_follows_every_feedback_frame_and_breaks_the_protocol(bench):
    bench.send(mit_enable(10, 10))
    bench.emulator.step(0.001)
    bench.received()
    bench.motor.garbage = True
    bench.emulator.step(0.1)
    frames = bench.received()
    garbage = []
    for msg in frames:
        try:
            if msg.is_remote_frame:
                raise InvalidFrame("remote")
            parse_frame(msg.arbitration_id, msg.data)
        except InvalidFrame:
            garbage.append(msg)
    assert len(garbage) == len(frames) // 2 == 20


def test_not_acknowledging_fills_the_senders_queue(bench):
    bench.emulator.acknowledge = False
    bench.send(*[Command(0, 0, 0)] * TX_QUEUE_LENGTH)
    with pytest.raises(can.CanOperationError):
        bench.send(Command(0, 0, 0))


def test_acknowledging_again_delivers_the_queued_frames(bench):
    bench.emulator.acknowledge = False
    bench.send(gains(20.0, 2.0))
    bench.emulator.step(0.01)
    assert bench.motor.kp == 0.0
    bench.emulator.acknowledge = True
    bench.emulator.step(0.001)
    assert bench.motor.kp == pytest.approx(20.0, rel=1e-6)


def test_bus_off_is_reported_as_a_socketcan_error_frame(bench):
    bench.emulator.inject_bus_off()
    (msg,) = bench.received()
    assert msg.is_error_frame and msg.arbitration_id & CAN_ERR_BUSOFF


def test_background_thread_advances_firmware_time_and_stops(bench):
    bench.emulator.start()
    deadline = time.monotonic() + 5.0
    while bench.emulator.time < 0.05 and time.monotonic() < deadline:
        time.sleep(0.01)
    bench.emulator.stop()
    stopped_at = bench.emulator.time
    time.sleep(0.02)
    assert stopped_at >= 0.05
    assert bench.emulator.time == stopped_at


def test_a_motor_moves_its_wrist_of_the_prime_world_through_the_wiring(robot):
    """A Sito on a wrist of the MuJoCo world (wired backwards, factory offset 0.1 rad) holds the raw position
    it is commanded; the joint itself sits at direction * (raw - offset)."""
    truth = truth_calibration(robot, Calibration({"left_wrist_pitch": JointCalibration(-1, 0.1)}))
    world = PrimeWorld(robot, truth, held=robot.hardware.erob_joints)
    channel = f"sito-emu-{uuid.uuid4().hex}"
    motor_bus, host = can.Bus(interface="virtual", channel=channel), can.Bus(interface="virtual", channel=channel)
    try:
        motor = SitoMotor(CAN_ID, world.plant(["left_wrist_pitch"]), torque_limit=4.8)
        emulator = SitoEmulator(motor_bus, [motor], world_step=world.step)
        for frame in (gains(20.0, 2.0), mit_enable(), Command(0, 0, position_to_counts(0.3))):
            ident, payload = pack_frame(CAN_ID, frame)
            host.send(can.Message(arbitration_id=ident, is_extended_id=True, data=payload), timeout=0.0)
        emulator.step(1.0)
        assert world.joint_positions()["left_wrist_pitch"] == pytest.approx(-0.2, abs=0.01)
        assert world.joint_positions()["left_shoulder_pitch"] == 0.0  # held: no device drives it
    finally:
        motor_bus.shutdown()
        host.shutdown()
