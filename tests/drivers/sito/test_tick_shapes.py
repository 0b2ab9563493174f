"""The compiled Sito tick runs with bounds checking off: each entry refuses an array shorter than the joints it
indexes, or a motor it does not have, and writes nothing: neither past the caller's buffer nor into the payloads."""

from __future__ import annotations

import numpy as np
import pytest

from humanoid_prime.drivers.sito._tick import SitoTick  # private to the package: the compiled kernel
from humanoid_prime.drivers.sito.protocol import HOST_PAYLOADS, MIT_FIELDS

JOINTS = 14  # the robot's arrays; the four motors are its last joints
GUARD = 1234.5


def tick(index=(10, 11, 12, 13)) -> SitoTick:
    n = len(index)
    raw = np.arange(3.0 * n).reshape(3, n) + 1.0
    return SitoTick(np.array(index, dtype=np.intp), np.ones((5, n)), np.zeros(n), raw, np.zeros((2, n)),
                    HOST_PAYLOADS, MIT_FIELDS)


def guarded(rows: int, columns: int, fill: float) -> tuple[np.ndarray, np.ndarray]:
    """A C-contiguous rows x columns array at the head of a larger buffer, and that buffer."""
    buffer = np.full(rows * columns + 64, GUARD)
    array = buffer[:rows * columns].reshape(rows, columns)
    array[:] = fill
    return array, buffer


def test_a_state_of_fewer_joints_than_the_motors_reach_is_refused_and_nothing_written():
    sito = tick()
    state, buffer = guarded(3, JOINTS - 4, 7.0)
    before = buffer.copy()
    with pytest.raises(ValueError, match=f"state is 3x{JOINTS - 4}, needs at least 3x{JOINTS}"):
        sito.read(state, 0.0)
    assert (buffer == before).all()
    assert not sito.late.any()
    with pytest.raises(ValueError, match=f"state is 2x{JOINTS}, needs at least 3x{JOINTS}"):
        sito.read(np.zeros((2, JOINTS)), 0.0)
    state = np.zeros((3, JOINTS))
    sito.read(state, 0.0)  # the robot's own size is read
    assert (state[:, 10:] != 0.0).all()


def test_a_command_of_fewer_joints_than_the_motors_reach_is_refused_and_no_payload_packed():
    sito = tick()
    command, _ = guarded(5, JOINTS - 4, 0.1)
    payloads = sito.payloads.copy()
    with pytest.raises(ValueError, match=f"command is 5x{JOINTS - 4}, needs at least 5x{JOINTS}"):
        sito.write(command, 0.0)
    with pytest.raises(ValueError, match=f"command is 4x{JOINTS}, needs at least 5x{JOINTS}"):
        sito.write(np.full((4, JOINTS), 0.1), 0.0)
    assert (sito.payloads == payloads).all()
    assert not sito.problems.any() and not sito.gains_due.any()


def test_a_motor_it_does_not_have_is_refused():
    sito = tick()
    for k in (4, -1):
        with pytest.raises(IndexError, match=f"no motor {k}: there are 4"):
            sito.gains_sent_at(k, 1.0)
    sito.gains_sent_at(3, 1.0)


def test_a_negative_joint_index_is_refused_when_the_kernel_is_built():
    with pytest.raises(ValueError, match=r"index\[1\] is -2"):
        tick((10, -2, 12, 13))
