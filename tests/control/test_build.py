"""Building the controllers from prime_controllers.yaml."""

from dataclasses import replace

import pytest

from humanoid_prime.control.controllers import build_controllers, resolve_policy
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import bundled


def test_controllers_come_in_staged_start_order(robot, config):
    assert list(build_controllers(robot, config)) == [
        "joint_state_broadcaster", "zero_torque_controller", "damping_controller", "standby_controller",
        "locomotion_controller", "remote_policy_controller"]


def test_a_bare_policy_name_is_the_bundled_file(config):
    assert resolve_policy(config) == bundled("standby_policy.onnx")


def test_another_policy_name_is_a_path_relative_to_the_controllers_file(config, tmp_path):
    (tmp_path / "policies").mkdir()
    (tmp_path / "policies" / "mine.onnx").write_bytes(b"")
    local = replace(config, path=tmp_path / "prime_controllers.yaml",
                    locomotion=replace(config.locomotion, policy="policies/mine.onnx"))
    assert resolve_policy(local) == tmp_path / "policies" / "mine.onnx"


def test_a_missing_policy_file_names_the_key_and_the_fix(config, tmp_path):
    missing = replace(config, locomotion=replace(config.locomotion, policy=str(tmp_path / "gone.onnx")))
    with pytest.raises(ConfigError, match="locomotion_controller.ros__parameters.policy: policy file .*gone.onnx"):
        resolve_policy(missing)


def test_a_standby_pose_outside_the_limits_is_refused(robot, config):
    poses = {**config.standby.poses, "reach": {"left_elbow_pitch": 0.5}}
    bad = replace(config, standby=replace(config.standby, poses=poses))
    with pytest.raises(ConfigError, match=r"poses.reach.left_elbow_pitch: left_elbow_pitch at 0.5 rad is outside "
                                          r"its limits \[-2.356, 0.0\]"):
        build_controllers(robot, bad)


@pytest.mark.parametrize(("edit", "key", "problem"), [
    (lambda c: replace(c, locomotion=replace(c.locomotion, sito_kp=120.0)), "locomotion_controller.ros__parameters"
     ".sito_kp", "120 is beyond the sito stiffness maximum of 100 (command_limits.sito.stiffness in "),
    (lambda c: replace(c, damping_kd=12.0), "damping_controller.ros__parameters.kd",
     "12 is beyond the sito damping maximum of 10"),
    (lambda c: replace(c, remote=replace(c.remote, erob_kd=60.0)), "remote_policy_controller.ros__parameters.erob_kd",
     "60 is beyond the erob damping maximum of 50"),
])
def test_a_mode_gain_beyond_its_familys_maximum_is_refused_at_load(robot, config, edit, key, problem):
    with pytest.raises(ConfigError) as caught:
        build_controllers(robot, edit(config))
    assert caught.value.key == key and problem in caught.value.problem


def test_an_erob_gain_may_exceed_the_sito_maximum(robot, config):
    build_controllers(robot, replace(config, remote=replace(config.remote, erob_kp=300.0)))
