"""Which Sito wrists are on the bus: the feedback frames heard from each CAN id.

The Sito protocol has no read request: a motor streams feedback only once enabled (select mode), at the
intervals the enable asked for. So a listener hears only wrists that something has enabled, and a probe that
must hear every wrist enables each limp first: zero gains, then MIT mode with feedback, then a command of zero
current, and a disable (reset) on every exit path. With zero gains and zero current the motor makes no torque.
"""

from __future__ import annotations

import contextlib
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

import can

from humanoid_prime.drivers.sito.protocol import (
    MODE_MIT,
    MOTOR_FRAME_TYPES,
    Command,
    Disable,
    Enable,
    Frame,
    FrameType,
    Gains,
    InvalidFrame,
    pack_frame,
    parse,
    split_arbitration_id,
)

PROBE_FEEDBACK_MS = 10
LIMP_PROBE: tuple[Frame, ...] = (Gains(0.0, 0.0), Enable(MODE_MIT, (PROBE_FEEDBACK_MS, PROBE_FEEDBACK_MS, 0)),
                                 Command(0, 0, 0))


def _send(bus: can.BusABC, can_id: int, frames: Iterable[Frame]) -> None:
    for frame in frames:
        ident, data = pack_frame(can_id, frame)
        bus.send(can.Message(arbitration_id=ident, is_extended_id=True, data=data), timeout=0.1)


@dataclass
class Heard:
    """What a listen heard: CAN id -> the valid feedback frames from it (by frame type), and CAN id -> (frames, the
    last one's problem) for frames of a motor's type that the protocol refuses (not counted as feedback)."""

    frames: dict[int, Counter[str]] = field(default_factory=dict)
    invalid: dict[int, tuple[int, str]] = field(default_factory=dict)


def listen(bus: can.BusABC, seconds: float, *, enable: Iterable[int] = ()) -> Heard:
    """The feedback heard from each CAN id in ``seconds``, each frame judged by the protocol (``parse``). The ids
    in ``enable`` are enabled limp first and disabled again on every exit path (the module's docstring); raises
    can.CanError when the bus refuses a frame."""
    probed = list(enable)
    heard = Heard()
    try:
        for can_id in probed:
            _send(bus, can_id, LIMP_PROBE)
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg = bus.recv(min(left, 0.1))
            except can.CanOperationError:  # a datagram that is no CAN frame (udp_multicast): not a wrist
                continue
            if msg is None or msg.is_error_frame or not msg.is_extended_id:
                continue
            split = split_arbitration_id(msg.arbitration_id)
            if split is None or split[1] not in MOTOR_FRAME_TYPES:
                continue  # foreign traffic, or a host's frame
            can_id, frame_type = split
            try:
                parse(frame_type, bytes(msg.data[:msg.dlc]), remote=msg.is_remote_frame, fd=msg.is_fd)
            except InvalidFrame as exc:  # a motor's frame type that breaks the protocol: no wrist's feedback
                count = heard.invalid[can_id][0] + 1 if can_id in heard.invalid else 1
                heard.invalid[can_id] = (count, str(exc))
                continue
            heard.frames.setdefault(can_id, Counter())[FrameType(frame_type).name.lower()] += 1
    finally:
        for can_id in probed:
            with contextlib.suppress(can.CanError):
                _send(bus, can_id, (Disable(),))
    return heard
