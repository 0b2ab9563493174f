"""The eRob process image never overflows: any double in any command interface gives a CSP target, velocity
offset and torque offset equal to the command's exact value in counts saturated at the PDO type (the torque
offset at the drive's +-3000 per mille), or the documented hold or follow; over the full float range."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from doubles.master import FakeMaster
from humanoid_prime.config.calibration import JointCalibration, load_calibration
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.drivers.ethercat.system import EthercatSystem

INT32 = (-(2**31), 2**31 - 1)
TORQUE_OFFSET = (-3000, 3000)  # per mille of the rated torque (ZeroErr EDS V1.5)
any_double = st.floats(allow_nan=True, allow_infinity=True)
interface = st.one_of(any_double, st.floats(-10.0, 10.0), st.sampled_from([0.0, math.nan]))


@pytest.fixture(scope="module")
def system(robot, tmp_path_factory):
    calibration = load_calibration(robot.hardware).with_joint("left_wrist_yaw", JointCalibration(-1, 0.3))
    master = FakeMaster()
    master.position_counts[:] = np.arange(10) * 1000 - 4321
    system = EthercatSystem(robot, calibration, update_rate=50.0, master=master,
                            config_dir=tmp_path_factory.mktemp("slaves"))
    system.configure()
    system.activate()
    system.read(0.0, StateArrays(robot.n))
    yield system
    system.shutdown()


def saturated(exact: float, low: int, high: int) -> int:
    return low if exact < low else high if exact > high else math.floor(exact + 0.5)


@settings(max_examples=300, deadline=None)
@given(values=st.tuples(*[interface] * 5))
@example(values=(1e308, 1e6, 0.0, 1e9, 1e9))
@example(values=(1.7e308, 0.0, 0.0, 0.0, 0.0))
@example(values=(-1e303, -1e303, 1e303, 1.0, 0.0))
def test_every_command_gives_a_process_image_within_its_types(robot, system, values):
    command = CommandArrays(robot.n)
    command.data[:] = np.array(values)[:, None]
    held = system.master.outputs["target_position"][system.ring].astype(float)
    system.write(0.0, command)
    outputs = system.master.outputs[system.ring]
    position, velocity, effort, stiffness, _ = values
    for k in range(len(system.joints)):
        factor, offset = system.command_factor[:, k].tolist(), system.command_offset[:, k].tolist()  # Python floats
        target = position * factor[0] + offset[0]
        if not math.isfinite(target):
            expected = held[k]
        elif stiffness == 0.0:
            expected = float(system.master.position_counts[system.ring[k]])
        else:
            expected = saturated(target, *INT32)
        assert outputs["target_position"][k] == expected, (k, target)
        feed = velocity * factor[1] + offset[1]
        assert outputs["velocity_offset"][k] == (saturated(feed, *INT32) if math.isfinite(feed) else 0)
        torque = effort * factor[2] + offset[2]
        assert outputs["torque_offset"][k] == (saturated(torque, *TORQUE_OFFSET) if math.isfinite(torque) else 0)
