"""The bundled files describe Prime as DESIGN §1 says."""

from humanoid_prime.config.calibration import load_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.description import ETHERCAT_BLOCK, MUJOCO_BLOCK, SITO_BLOCK
from humanoid_prime.modes import Mode

CANONICAL = (
    "left_shoulder_pitch", "left_shoulder_roll", "left_shoulder_yaw", "left_elbow_pitch",
    "left_wrist_roll", "left_wrist_pitch", "left_wrist_yaw",
    "right_shoulder_pitch", "right_shoulder_roll", "right_shoulder_yaw", "right_elbow_pitch",
    "right_wrist_roll", "right_wrist_pitch", "right_wrist_yaw",
)


def test_canonical_joint_order(robot):
    assert robot.names == CANONICAL


def test_wrist_yaw_is_ring_position_4_and_9(robot):
    assert robot.joints[robot.index("left_wrist_yaw")].ring_position == 4
    assert robot.joints[robot.index("right_wrist_yaw")].ring_position == 9


def test_ring_positions_follow_design(robot):
    ring = {j.name: j.ring_position for j in robot.joints if j.family == "erob"}
    assert list(ring.values()) == [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]


def test_sito_can_ids(robot):
    ids = {j.name: j.can_id for j in robot.joints if j.family == "sito"}
    assert ids == {"left_wrist_roll": 0x16, "left_wrist_pitch": 0x17,
                   "right_wrist_roll": 0x26, "right_wrist_pitch": 0x27}


def test_limits_from_description(robot):
    lim = {j.name: (j.lower, j.upper) for j in robot.joints}
    assert lim["left_shoulder_pitch"] == (-3.142, 0.785)
    assert lim["left_shoulder_roll"] == (-1.571, 1.920)
    assert lim["right_shoulder_roll"] == (-1.920, 1.571)
    assert lim["left_elbow_pitch"] == (-2.356, 0.0)
    assert lim["right_wrist_roll"] == (-0.698, 0.698)
    assert lim["right_wrist_pitch"] == (-0.785, 0.785)
    assert lim["left_wrist_yaw"] == (-1.571, 1.571)


def test_effort_limits(robot):
    eff = {j.name: j.effort_limit for j in robot.joints}
    assert eff["left_shoulder_pitch"] == 30.0
    assert eff["left_wrist_yaw"] == 10.0
    assert eff["left_wrist_roll"] == 4.8


def test_real_description_has_two_blocks(robot):
    ec = robot.description.block(ETHERCAT_BLOCK)
    can = robot.description.block(SITO_BLOCK)
    assert len(ec.joints) == 10 and len(can.joints) == 4
    assert ec.joint_params["left_wrist_yaw"]["position"] == "4"
    assert can.joint_params["right_wrist_pitch"]["can_id"] == "39"


def test_sim_description_has_one_block(sim_robot):
    (block,) = sim_robot.description.blocks
    assert block.name == MUJOCO_BLOCK and block.joints == CANONICAL


def test_bundled_calibration_is_identity(robot):
    cal = load_calibration(robot.hardware)
    assert all(c.direction == 1 and c.homing_offset == 0.0 for c in cal.joints.values())


def test_mode_gains_table(robot):
    gains = load_controllers(robot.names).mode_gains()
    assert gains == {Mode.ZERO_TORQUE: (0.0, 0.0), Mode.DAMPING: (0.0, 6.0), Mode.STANDBY: (20.0, 2.0),
                     Mode.LOCOMOTION: (20.0, 2.0), Mode.REMOTE: (20.0, 2.0)}


def test_update_rate_is_50_hz(robot):
    assert load_controllers(robot.names).update_rate == 50.0
