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
    pack_frame,
    split_arbitration_id,
)

PROBE_FEEDBACK_MS = 10
LIMP_PROBE: tuple[Frame, ...] = (Gains(0.0, 0.0), Enable(MODE_MIT, (PROBE_FEEDBACK_MS, PROBE_FEEDBACK_MS, 0)),
                                 Command(0, 0, 0))


def _send(bus: can.BusABC, can_id: int, frames: Iterable[Frame]) -> None:
    for frame in frames:
        ident, data = pack_frame(can_id, frame)
        bus.send(can.Message(arbitration_id=ident, is_extended_id=True, data=data), timeout=0.1)


def listen(bus: can.BusABC, seconds: float, *, enable: Iterable[int] = ()) -> dict[int, Counter[str]]:
    """CAN id -> feedback frames heard from it (by frame type) in ``seconds``. The ids in ``enable`` are enabled
    limp first and disabled again on every exit path (the module's docstring); raises can.CanError when the bus
    refuses a frame."""
    probed = list(enable)
    heard: dict[int, Counter[str]] = {}
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
            if split is not None and split[1] in MOTOR_FRAME_TYPES:
                heard.setdefault(split[0], Counter())[FrameType(split[1]).name.lower()] += 1
    finally:
        for can_id in probed:
            with contextlib.suppress(can.CanError):
                _send(bus, can_id, (Disable(),))
    return heard
