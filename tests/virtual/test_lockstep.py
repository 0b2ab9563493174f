"""The lockstep Prime's devices receive every command exactly as the host's drivers put it on the wire.

Beside the rig stand the same drivers on the buses of a run: an ``EthercatSystem`` on a ring that reports what the
rig's ring reported (``MirrorMaster``), and a ``SitoSystem`` on a virtual CAN channel with a sniffer. Both sides get
the same command, drawn over every float (NaN, infinities, huge, negative gains, subnormals); after each write every
eRob drive must hold the process image the reference sent (controlword, CSP target, offsets, mode), and every Sito
motor the last gains and MIT command the reference sent. A drive may be in fault for the command (a disabled drive
follows the joint)."""

from __future__ import annotations

import math
import random
from collections.abc import Iterator
from dataclasses import astuple, dataclass, field

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doubles.master import MirrorMaster
from doubles.sito import Rig
from humanoid_prime.config.calibration import Calibration, JointCalibration
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD
from humanoid_prime.drivers.ethercat.system import EthercatSystem
from humanoid_prime.drivers.sito.protocol import Command, Gains, parse_frame
from humanoid_prime.sim.demo import START_POSE
from humanoid_prime.virtual.lockstep import LockstepPrime

UPDATE_RATE = 50.0
NO_COMMAND = (math.nan, 0.0, 0.0, 0.0, 0.0)
RX_FIELDS = ("controlword", "target_position", "velocity_offset", "torque_offset", "mode_of_operation")


def host_calibration(robot: Robot) -> Calibration:
    """Mixed directions and offsets, so every factor and offset of the mapping is exercised."""
    rng = random.Random(42)
    return Calibration({j: JointCalibration(rng.choice((1, -1)), round(rng.uniform(-0.5, 0.5), 4))
                        for j in robot.names})


@dataclass(repr=False)  # hypothesis prints the fixtures of a failing example
class Pair:
    """The rig's components and the reference drivers, fed the same commands and the same inputs."""

    robot: Robot
    rig: LockstepPrime
    ethercat: EthercatSystem
    mirror: MirrorMaster
    sito: Rig
    now: float = 0.0
    rig_state: StateArrays = field(init=False)
    reference_state: StateArrays = field(init=False)
    last: dict[int, dict[type, Gains | Command]] = field(default_factory=dict)  # CAN id -> last frames sent

    def __post_init__(self) -> None:
        self.rig_state, self.reference_state = StateArrays(self.robot.n), StateArrays(self.robot.n)

    def tick(self, command: CommandArrays) -> None:
        self.now += 1.0 / UPDATE_RATE
        for component in self.rig.components:
            component.read(self.now, self.rig_state)
        np.copyto(self.mirror.feed, self.rig.ring.inputs)  # what the rig's drives reported, to the reference
        self.ethercat.read(self.now, self.reference_state)
        self.sito.system.read(self.now, self.reference_state)
        for component in (*self.rig.components, self.ethercat, self.sito.system):
            component.write(self.now, command)
        for arbitration, data in self.sito.host_frames():
            can_id, frame = parse_frame(arbitration, data)
            self.last.setdefault(can_id, {})[type(frame)] = frame

    def disagreements(self) -> list[str]:
        found = []
        for position, drive in enumerate(self.rig.ring.drives):
            held = (drive.controlword.value, drive.target_position.value, drive.velocity_offset.value,
                    drive.torque_offset.value, drive.mode.value)
            sent = tuple(self.mirror.sent[position][name].item() for name in RX_FIELDS)
            if held != sent:
                found.append(f"ring {position}: the drive holds {dict(zip(RX_FIELDS, held, strict=True))}, "
                             f"the host sent {dict(zip(RX_FIELDS, sent, strict=True))}")
        for motor in self.rig.sito.values():
            gains, command = self.last[motor.can_id].get(Gains), self.last[motor.can_id].get(Command)
            held_gains = (motor.kp_fw, motor.kd_fw)
            sent_gains = (gains.kp_fw, gains.kd_fw) if gains is not None else (0.0, 0.0)
            if held_gains != sent_gains:
                found.append(f"Sito {motor.can_id}: the motor holds gains {held_gains}, the host sent {sent_gains}")
            held = (motor.current_mA, motor.velocity_counts, motor.position_counts)
            if command is not None and held != astuple(command):
                found.append(f"Sito {motor.can_id}: the motor holds {held}, the host sent {command}")
        return found


@pytest.fixture(scope="module")
def pair(robot: Robot) -> Iterator[Pair]:
    calibration = host_calibration(robot)
    rig = LockstepPrime(robot, calibration, calibration, update_rate=UPDATE_RATE, physics_rate=250.0,
                        initial_pose=START_POSE)
    sito = Rig(robot, calibration)
    reference: EthercatSystem | None = None
    try:
        for component in rig.components:
            component.configure()
            component.activate()
        rated = int(next(iter(rig.erob.values())).od.value(0x6076, 0))
        mirror = MirrorMaster(rig.ring.inputs, rated_torque_mnm=rated, update_rate=UPDATE_RATE)
        reference = EthercatSystem(robot, calibration, update_rate=UPDATE_RATE, master=mirror)
        reference.configure()
        reference.activate()
        sito.activate()
        sito.sniffed()
        yield Pair(robot, rig, reference, mirror, sito)
    finally:
        if reference is not None:
            reference.shutdown()
        sito.close()
        for component in rig.components:
            component.shutdown()
        rig.close()


def commands(n: int) -> st.SearchStrategy[list[tuple[float, ...]]]:
    value = st.one_of(st.floats(allow_nan=True, allow_infinity=True),  # every float, subnormals and huge ones too
                      st.floats(-20.0, 20.0),
                      st.sampled_from([0.0, -0.0, math.nan, math.inf, -math.inf, 0.5 / COUNTS_PER_RAD, 1e300]))
    joint = st.one_of(st.tuples(value, value, value, value, value), st.just(NO_COMMAND))
    return st.lists(joint, min_size=n, max_size=n)


def as_command(robot: Robot, rows: list[tuple[float, ...]]) -> CommandArrays:
    command = CommandArrays(robot.n)
    command.data[:] = np.array(rows, dtype=float).T
    return command


@settings(max_examples=300)
@given(data=st.data())
def test_every_command_reaches_the_devices_as_the_host_drivers_send_it(robot, pair, data):
    # each example starts from the same held targets on both sides: a plain command first
    pair.tick(as_command(robot, [(0.1, 0.0, 0.0, 20.0, 2.0)] * robot.n))
    faulted = data.draw(st.sets(st.sampled_from(sorted(robot.hardware.erob_joints)), max_size=3), label="faulted")
    for joint in faulted:
        pair.rig.inject_fault(joint, 0x8500)
    for rows in data.draw(st.lists(commands(robot.n), min_size=1, max_size=3), label="commands"):
        pair.tick(as_command(robot, rows))
        assert pair.disagreements() == []
    if faulted:  # the operator's reset: both sides re-enable the drives before the next example
        pair.rig.ethercat.reset_faults()
        pair.ethercat.reset_faults()
        for _ in range(20):
            pair.tick(as_command(robot, [NO_COMMAND] * robot.n))
            if all(drive.csp_enabled for drive in pair.rig.erob.values()):
                break
        assert all(drive.csp_enabled for drive in pair.rig.erob.values())


@pytest.mark.parametrize("crossed", [False, True])
def test_the_rig_records_an_arm_touching_the_other_arm(robot, crossed):
    """The truths a calibration is judged by include that no arm touched the other or the body: the rig sees arms
    crossed in front of the chest, and nothing in the start pose."""
    identity = Calibration({j: JointCalibration(1, 0.0) for j in robot.names})
    pose = dict(START_POSE)
    if crossed:
        pose.update({"left_shoulder_roll": -1.0, "right_shoulder_roll": 1.0, "left_shoulder_pitch": -1.2,
                     "right_shoulder_pitch": -1.2, "left_elbow_pitch": -1.2, "right_elbow_pitch": -1.2})
    rig = LockstepPrime(robot, identity, identity, update_rate=UPDATE_RATE, physics_rate=250.0, initial_pose=pose)
    try:
        rig.step()
        touching = set(rig.body_contacts)
    finally:
        rig.close()
    if crossed:
        assert ("left_forearm_link", "right_forearm_link") in touching
    else:
        assert touching == set()
