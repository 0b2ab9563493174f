"""Every entry of the compiled controller kernels refuses an array shorter than it indexes (the kernels run with
bounds checking off): a ValueError naming the array and the shape it needs, and nothing written."""

import numpy as np
import pytest

# private to control/: the compiled kernels themselves, whose contract these tests pin
from humanoid_prime.control._tick import SHAPE, Blend, BodyKernel, CommandCheck, Copy, FollowMeasured, Inbox
from humanoid_prime.control.body import BodyCheck, mujoco_library

N = 14


def bounds() -> CommandCheck:
    return CommandCheck(np.full(N, -1.0), np.full(N, 1.0), np.full((4, N), 10.0), 0.05)


def test_the_command_check_refuses_a_command_of_another_shape_and_clips_nothing():
    short = np.full((5, N - 4), 0.0)
    short[0] = 2.0  # a target the check would clip onto the limit
    with pytest.raises(ValueError, match=f"command is 5x{N - 4}, needs 5x{N}"):
        bounds().check(short)
    assert (short[0] == 2.0).all()
    with pytest.raises(ValueError, match=f"command is 4x{N}, needs 5x{N}"):
        bounds().check(np.zeros((4, N)))


def test_the_inbox_refuses_a_short_row_and_leaves_the_inbox_as_it_was():
    inbox = np.full((5, N), 7.0)
    door = Inbox(inbox, bounds())
    rows = [np.zeros(N)] * 5
    rows[4] = np.zeros(N - 1)
    assert door.take(*rows) == SHAPE
    assert (inbox == 7.0).all()


def test_copy_refuses_arrays_of_different_shapes_and_copies_nothing():
    copy, dst = Copy(), np.full((3, N), 7.0)
    copy.run(dst, np.zeros((3, N)))  # bound to these two
    assert (dst == 0.0).all()
    dst[:] = 7.0
    with pytest.raises(ValueError, match=rf"shape \(3, {N - 4}\) into one of shape \(3, {N}\)"):
        copy.run(dst, np.zeros((3, N - 4)))
    assert (dst == 7.0).all()


def test_follow_measured_refuses_a_short_command_or_position_and_writes_nothing():
    follow = FollowMeasured(np.full(N, -1.0), np.full(N, 1.0))
    command = np.full((5, N - 4), 7.0)
    with pytest.raises(ValueError, match=f"position has {N} entries and command is 5x{N - 4}, need {N} and 5x{N}"):
        follow.run(np.zeros(N), command)
    assert (command == 7.0).all()
    command = np.full((5, N), 7.0)
    with pytest.raises(ValueError, match=f"position has {N - 4} entries"):
        follow.run(np.zeros(N - 4), command)
    assert (command == 7.0).all()


def test_blend_refuses_a_short_command_or_delta_and_writes_nothing():
    command = np.full((5, N - 4), 7.0)
    with pytest.raises(ValueError, match=f"start has {N} entries, delta {N}, command is 5x{N - 4}: need 5x{N}"):
        Blend().run(np.zeros(N), np.zeros(N), 0.5, 1.0, 10.0, 1.0, command)
    assert (command == 7.0).all()
    command = np.full((5, N), 7.0)
    with pytest.raises(ValueError, match=f"delta {N - 1}"):
        Blend().run(np.zeros(N), np.zeros(N - 1), 0.5, 1.0, 10.0, 1.0, command)
    assert (command == 7.0).all()


@pytest.fixture(scope="module")
def body(robot):
    return BodyCheck(robot, robot.hardware.collision_margin)


def test_the_body_kernel_refuses_a_short_command_measurement_or_frame_and_moves_nothing(body, robot):
    kernel, n = body.kernel, robot.n
    qpos = body.data.qpos.copy()
    for command, measured, velocity, shape in (
            (np.zeros((5, n - 4)), np.zeros(n), np.zeros(n), f"command is 5x{n - 4}"),
            (np.zeros((5, n)), np.zeros(n - 1), np.zeros(n), f"measured and velocity have {n - 1} and {n}"),
            (np.zeros((5, n)), np.zeros(n), np.zeros(n - 1), f"measured and velocity have {n} and {n - 1}")):
        with pytest.raises(ValueError, match=shape):
            kernel.check(command, measured, velocity, 0.0)
        with pytest.raises(ValueError, match=shape):
            kernel.pose(command, measured, velocity, 0.0)
    assert (body.data.qpos == qpos).all()
    with pytest.raises(ValueError, match=f"scale, shift and known have {n}, {n - 1} and {n} entries, need {n} each"):
        kernel.frame(np.ones(n), np.zeros(n - 1), np.ones(n, dtype=np.uint8))
    with pytest.raises(IndexError, match=f"no pair {len(body.pairs)}"):
        kernel.distance_of(len(body.pairs), 1.0)
    with pytest.raises(IndexError, match="no pair -1"):
        kernel.distance_of(-1, 1.0)


def test_the_body_kernel_refuses_joints_and_geoms_the_model_does_not_have(body, robot):
    m = body.model
    qadr = np.ascontiguousarray(m.jnt_qposadr[body.joint_ids], dtype=np.intp)
    lower, upper = np.ascontiguousarray(robot.lower), np.ascontiguousarray(robot.upper)
    chains, live = np.zeros(len(body.pairs), dtype=np.uint64), np.ones(len(body.pairs), dtype=np.uint8)
    beyond = qadr.copy()
    beyond[3] = m.nq
    with pytest.raises(ValueError, match=f"qadr\\[3\\] is {m.nq}, outside the model's {m.nq} qpos"):
        BodyKernel(mujoco_library(), m, body.data, beyond, lower, upper, body.pairs, chains, live, 0.01)
    pairs = body.pairs.copy()
    pairs[0, 1] = m.ngeom
    with pytest.raises(ValueError, match=f"pairs\\[0, 1\\] is {m.ngeom}, outside the model's {m.ngeom} geoms"):
        BodyKernel(mujoco_library(), m, body.data, qadr, lower, upper, pairs, chains, live, 0.01)
    pairs[0, 1] = -1
    with pytest.raises(ValueError, match="pairs\\[0, 1\\] is -1"):
        BodyKernel(mujoco_library(), m, body.data, qadr, lower, upper, pairs, chains, live, 0.01)
    BodyKernel(mujoco_library(), m, body.data, qadr, lower, upper, body.pairs, chains, live, 0.01)  # as given: fine
