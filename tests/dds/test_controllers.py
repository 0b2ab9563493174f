"""Prime's modes as the controller manager's controllers, and the run as parameters: what ``ros2 control`` and
``ros2 param`` show, without ROS."""

from __future__ import annotations

import pytest

from humanoid_prime.dds.controllers import SwitchRefused, controllers, mode_to_activate
from humanoid_prime.dds.parameters import REMOTE_TIMEOUT, run_parameters
from humanoid_prime.modes import Mode


@pytest.fixture
def manager(manager):
    """The DDS tests' manager, in DAMPING."""
    manager.request_mode(Mode.DAMPING)
    manager.tick(0.0)
    return manager


def test_the_broadcaster_and_the_active_mode_are_active_and_the_mode_claims_every_command(manager):
    listed = {c.name: c for c in controllers(manager)}
    assert list(listed) == ["joint_state_broadcaster", "zero_torque_controller", "damping_controller",
                            "standby_controller", "locomotion_controller", "remote_policy_controller"]
    assert [c.name for c in listed.values() if c.state == "active"] == ["joint_state_broadcaster", "damping_controller"]
    assert len(listed["damping_controller"].claimed_interfaces) == 14 * 5
    assert "left_elbow_pitch/stiffness" in listed["damping_controller"].claimed_interfaces
    assert listed["standby_controller"].claimed_interfaces == ()
    assert listed["standby_controller"].type == "prime_controllers/StandbyController"
    assert listed["joint_state_broadcaster"].type == "joint_state_broadcaster/JointStateBroadcaster"
    assert listed["damping_controller"].update_rate == 100


def test_a_switch_activates_one_mode_controller(manager):
    assert mode_to_activate(manager, ["standby_controller"], ["damping_controller"], strict=True) is Mode.STANDBY
    assert mode_to_activate(manager, ["standby_controller"], [], strict=True) is Mode.STANDBY
    assert mode_to_activate(manager, [], [], strict=True) is None


@pytest.mark.parametrize(("activate", "deactivate", "reason"), [
    (["fly_controller"], [], "no controller named fly_controller"),
    (["standby_controller", "remote_policy_controller"], [], "one mode controller is active at a time"),
    ([], ["damping_controller"], "cannot be deactivated alone"),
    (["standby_controller"], ["remote_policy_controller"], "remote_policy_controller is not active"),
    ([], ["joint_state_broadcaster"], "always active"),
])
def test_a_switch_prime_cannot_make_is_refused_with_the_reason(manager, activate, deactivate, reason):
    with pytest.raises(SwitchRefused, match=reason):
        mode_to_activate(manager, activate, deactivate, strict=True)


def test_best_effort_skips_names_that_are_not_prime_controllers(manager):
    assert mode_to_activate(manager, ["fly_controller", "standby_controller"], [], strict=False) is Mode.STANDBY


def test_the_parameters_describe_the_run_and_only_the_remote_timeout_is_settable(manager, sim_robot):
    manager.configuration = {"hardware": {"path": "/x/prime_hardware.yaml", "sha256": "ab" * 32}}
    parameters = {p.name: p for p in run_parameters(manager, backend="rclpy", control=True)}
    assert parameters["backend"].value == "rclpy" and parameters["control"].value is True
    assert parameters["update_rate"].value == 100.0
    assert parameters["joints"].value == list(sim_robot.names)
    assert parameters["config.hardware.sha256"].value == "ab" * 32
    assert parameters["modes.STANDBY.erob_kp"].value == 20.0 and parameters["modes.DAMPING.erob_kd"].value == 6.0
    assert parameters["robot"].value == "prime_dummy"
    assert [name for name, p in parameters.items() if p.bounds is not None] == [REMOTE_TIMEOUT]
    timeout = parameters[REMOTE_TIMEOUT]
    assert timeout.value == 0.1 and timeout.bounds == (0.02, 0.5)
    assert timeout.apply is not None
    timeout.apply(0.25)
    assert manager.controllers["remote_policy_controller"].timeout == 0.25
