"""The compiled eRob tick runs with bounds checking off: each entry refuses an array shorter than the joints it
indexes (a state or command of fewer columns than the robot's, fewer reset flags than drives) with a ValueError
naming it, and writes nothing: neither past the caller's buffer nor into the process image."""

from __future__ import annotations

import numpy as np
import pytest

from doubles.master import FakeMaster
from humanoid_prime.config.calibration import load_calibration
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.drivers.ethercat.system import EthercatSystem

GUARD = 1234.5  # what lies past the short array, in the same allocation


@pytest.fixture
def system(robot, tmp_path):
    master = FakeMaster()
    master.position_counts[:] = np.arange(10) * 1000 - 4321
    system = EthercatSystem(robot, load_calibration(robot.hardware), update_rate=50.0, master=master,
                            config_dir=tmp_path)
    system.configure()
    system.activate()
    yield system
    system.shutdown()


def guarded(rows: int, columns: int, fill: float) -> tuple[np.ndarray, np.ndarray]:
    """A C-contiguous rows x columns array at the head of a larger buffer, and that buffer: a write past the array
    lands in the buffer's tail (GUARD) instead of the heap."""
    buffer = np.full(rows * columns + 64, GUARD)
    array = buffer[:rows * columns].reshape(rows, columns)
    array[:] = fill
    return array, buffer


def test_a_state_of_fewer_joints_than_the_robot_is_refused_and_nothing_written(system, robot):
    assert max(system.indices) == robot.n - 1  # the eRob joints reach the last column of the robot's arrays
    state = StateArrays(robot.n - 4)
    state.data, buffer = guarded(3, robot.n - 4, 7.0)
    before = buffer.copy()
    with pytest.raises(ValueError, match=f"state is 3x{robot.n - 4}, needs at least 3x{robot.n}"):
        system.read(0.0, state)
    assert (buffer == before).all()
    system.read(0.0, StateArrays(robot.n))  # the robot's own size is read


def test_a_command_of_fewer_joints_than_the_robot_is_refused_and_the_process_image_untouched(system, robot):
    system.read(0.0, StateArrays(robot.n))
    command = CommandArrays(robot.n - 4)
    command.data, _ = guarded(5, robot.n - 4, 0.1)
    outputs = system.master.outputs.copy()
    with pytest.raises(ValueError, match=f"command is 5x{robot.n - 4}, needs at least 5x{robot.n}"):
        system.write(0.0, command)
    assert (system.master.outputs == outputs).all()
    with pytest.raises(ValueError, match=f"command is 4x{robot.n}, needs at least 5x{robot.n}"):
        system._tick.write(np.zeros((4, robot.n)))
    assert (system.master.outputs == outputs).all()


def test_fewer_reset_flags_than_drives_are_refused_and_no_controlword_written(system, robot):
    system.read(0.0, StateArrays(robot.n))
    tick, drives = system._tick, len(system.joints)
    outputs = system.master.outputs.copy()
    with pytest.raises(ValueError, match=f"reset has {drives - 1} entries, needs at least {drives}"):
        tick.controlwords(np.ones(drives - 1, dtype=np.uint8))
    with pytest.raises(ValueError, match=f"reset has {drives - 1} entries, needs at least {drives}"):
        tick.write(np.zeros((5, robot.n)), np.ones(drives - 1, dtype=np.uint8))
    assert (system.master.outputs == outputs).all()


def test_a_negative_joint_index_is_refused_when_the_kernel_is_bound(system):
    system.indices = system.indices.copy()
    system.indices[2] = -1
    with pytest.raises(ValueError, match=r"index\[2\] is -1"):
        system._bind_views()
