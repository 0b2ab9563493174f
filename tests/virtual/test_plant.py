"""The plants the emulated drives move: independent inertias, and Prime's arms in MuJoCo."""

from __future__ import annotations

import numpy as np
import pytest

from humanoid_prime.config.calibration import JointCalibration, load_calibration
from humanoid_prime.virtual.plant import InertiaPlant, PrimeWorld, ring_order

DT = 0.001


def steps(plant, seconds: float, torque: np.ndarray | None = None, braked: np.ndarray | None = None) -> None:
    torque = np.zeros(plant.n) if torque is None else torque
    braked = np.zeros(plant.n, dtype=bool) if braked is None else braked
    for _ in range(round(seconds / DT)):
        plant.step(torque, braked, DT)


def test_inertia_accelerates_as_torque_over_inertia():
    plant = InertiaPlant(np.array([0.5]))
    steps(plant, 1.0, torque=np.array([1.0]))
    assert float(plant.qd[0]) == pytest.approx(2.0, rel=1e-6)
    assert float(plant.q[0]) == pytest.approx(1.0, rel=0.01)


def test_inertia_gravity_pulls_a_raised_joint_towards_hanging():
    plant = InertiaPlant(np.array([0.5]), gravity=np.array([5.0]), friction=np.array([2.0]))
    plant.q[0] = 0.5
    steps(plant, 5.0)
    assert abs(float(plant.q[0])) < 0.01


def test_inertia_hard_stop_stops_the_joint():
    plant = InertiaPlant(np.array([0.5]), upper=np.array([0.2]))
    steps(plant, 1.0, torque=np.array([2.0]))
    assert float(plant.q[0]) == pytest.approx(0.2, abs=0.005)


def test_arms_layout_repeats_per_arm():
    plant = InertiaPlant.arms(10)
    assert plant.inertia[0] == plant.inertia[5] and plant.inertia[4] == plant.inertia[9]


@pytest.fixture
def mujoco_plant(robot):
    calibration = load_calibration(robot.hardware).with_joint("left_wrist_yaw", JointCalibration(-1, 0.3))
    return PrimeWorld(robot, calibration, held=robot.hardware.sito_joints).plant(ring_order(robot), clock=True)


def test_mujoco_ring_positions_read_raw_angles_through_the_calibration(mujoco_plant):
    assert mujoco_plant.n == 10
    assert float(mujoco_plant.q[4]) == pytest.approx(0.3)  # left_wrist_yaw at 0 rad, direction -1, offset 0.3


def test_mujoco_torque_acts_in_the_raw_frame(mujoco_plant):
    torque = np.zeros(10)
    torque[4] = 0.5
    steps(mujoco_plant, 0.2, torque=torque)
    assert float(mujoco_plant.q[4]) > 0.3 + 0.01


def test_mujoco_raised_arm_falls_unless_braked(mujoco_plant):
    mujoco_plant.q[0] = -1.0  # left shoulder pitch raised forward
    mujoco_plant.q[5] = -1.0
    braked = np.zeros(10, dtype=bool)
    braked[5] = True
    steps(mujoco_plant, 0.3, braked=braked)
    assert float(mujoco_plant.q[0]) > -0.8
    assert float(mujoco_plant.q[5]) == pytest.approx(-1.0)


def test_coulomb_friction_holds_a_link_at_rest_against_a_smaller_torque():
    plant = InertiaPlant(np.array([0.5]), coulomb=np.array([0.3]))
    steps(plant, 0.5, torque=np.array([0.2]))
    assert float(plant.q[0]) == 0.0 and float(plant.qd[0]) == 0.0


def test_coulomb_friction_takes_its_share_of_a_larger_torque():
    plant = InertiaPlant(np.array([0.5]), coulomb=np.array([0.3]))
    steps(plant, 1.0, torque=np.array([0.8]))
    assert float(plant.qd[0]) == pytest.approx((0.8 - 0.3) / 0.5, rel=1e-3)


def test_coulomb_friction_stops_a_coasting_link_without_reversing_it():
    plant = InertiaPlant(np.array([0.5]), coulomb=np.array([0.5]))
    plant.qd[0] = 0.2
    steps(plant, 1.0)
    assert float(plant.qd[0]) == 0.0
    assert float(plant.q[0]) == pytest.approx(0.2 * 0.2 / 2.0, rel=0.02)  # v^2 / (2 a) with a = 1 rad/s^2


def test_a_braked_joint_holds_whatever_torque_acts_on_it():
    plant = InertiaPlant(np.array([0.5, 0.5]))
    plant.q[:] = 0.5
    steps(plant, 0.5, torque=np.array([1.0, 1.0]), braked=np.array([True, False]))
    assert float(plant.q[0]) == 0.5
    assert float(plant.q[1]) == pytest.approx(0.5 + 0.5 * 2.0 * 0.5**2, rel=0.01)
