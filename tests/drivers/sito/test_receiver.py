"""What the Sito receive thread keeps of each frame (``FeedbackReceiver``), fed frames as the Notifier hands them."""

import errno

import can
import numpy as np
import pytest

from humanoid_prime.drivers.sito.bus import CAN_ERR_BUSOFF
from humanoid_prime.drivers.sito.protocol import FEEDBACK1, FEEDBACK2, FrameType, arbitration_id
from humanoid_prime.drivers.sito.receiver import FeedbackReceiver

IDS = (22, 23, 38, 39)


@pytest.fixture
def receiver():
    now = iter(float(t) for t in range(1, 1000))
    return FeedbackReceiver(IDS, clock=lambda: next(now))


def frame(can_id: int, frame_type: int, data: bytes, **fields: object) -> can.Message:
    return can.Message(arbitration_id=arbitration_id(can_id, frame_type), is_extended_id=True, data=data, **fields)


def test_feedback_1_gives_velocity_and_current_and_feedback_2_the_output_position(receiver):
    receiver.on_message_received(frame(38, FrameType.FEEDBACK1, FEEDBACK1.pack(0, 0, -120, 2048)))
    receiver.on_message_received(frame(38, FrameType.FEEDBACK2, FEEDBACK2.pack(999, -5000)))
    assert receiver.raw[:, 2].tolist() == [-5000.0, 2048.0, -120.0]
    assert receiver.stamp[:, 2].tolist() == [1.0, 2.0]
    assert np.isneginf(receiver.stamp[:, [0, 1, 3]]).all()  # the others not heard from
    assert receiver.frames == 2 and receiver.invalid_frames == 0


def test_host_frames_foreign_ids_and_other_motors_are_passed_over_quietly(receiver):
    receiver.on_message_received(frame(38, FrameType.COMMAND, bytes(8)))  # our own echo
    receiver.on_message_received(frame(40, FrameType.FEEDBACK2, FEEDBACK2.pack(0, 7)))  # a Sito that is not ours
    receiver.on_message_received(can.Message(arbitration_id=0x123, is_extended_id=False, data=bytes(8)))
    assert receiver.frames == 3 and receiver.invalid_frames == 0 and np.isneginf(receiver.stamp).all()


def test_a_frame_that_breaks_the_protocol_is_counted_and_described(receiver):
    receiver.on_message_received(frame(22, FrameType.FEEDBACK2, bytes(6)))
    assert receiver.invalid_frames == 1 and receiver.last_invalid_stamp == 1.0
    assert receiver.last_invalid.startswith("id 0x050616B2 dlc 6: ")
    receiver.on_message_received(frame(22, 0x7F, bytes(8)))
    assert receiver.invalid_frames == 2 and receiver.last_invalid == "id 0x0506167F dlc 8: unknown frame type"


def test_feedback_0_and_3_are_counted_not_decoded(receiver):
    receiver.on_message_received(frame(22, FrameType.FEEDBACK0, bytes(8)))
    receiver.on_message_received(frame(22, FrameType.FEEDBACK3, bytes(8)))
    assert receiver.undecoded_frames == 2 and receiver.invalid_frames == 0


def test_a_bus_off_error_frame_is_noted_until_reset(receiver):
    receiver.on_message_received(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True))
    assert receiver.bus_off
    receiver.reset()
    assert not receiver.bus_off


def test_a_receive_error_is_the_interface_down_or_an_undecodable_frame(receiver):
    receiver.on_error(can.CanOperationError("Network is down", error_code=errno.ENETDOWN))
    assert receiver.down_error == "Network is down [Error Code 100]" and receiver.invalid_frames == 0
    receiver.on_error(ValueError("bad bytes"))
    assert receiver.invalid_frames == 1 and receiver.last_invalid == "undecodable frame: bad bytes"
