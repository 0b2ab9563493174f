"""The Sito wrists' feedback as it arrives: a python-can listener, run in the Notifier's thread, that keeps the
latest valid 0xB1/0xB2 of each motor (raw counts, and when each came) and notes what is wrong on the bus (frames
that break the protocol, bus off, the interface gone). ``SitoSystem.read`` takes the arrays under ``lock``."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import can
import numpy as np

from humanoid_prime.drivers.sito.bus import CAN_ERR_BUSOFF, is_interface_down
from humanoid_prime.drivers.sito.protocol import (
    FEEDBACK1,
    FEEDBACK2,
    HOST_FRAME_TYPES,
    ID_PREFIX,
    ID_PREFIX_MASK,
    UNDECODED_FEEDBACK_TYPES,
    FrameType,
    framing_problem,
)

_HOST_TYPES = frozenset(int(t) for t in HOST_FRAME_TYPES)
_FEEDBACK1 = int(FrameType.FEEDBACK1)
_FEEDBACK2 = int(FrameType.FEEDBACK2)
_UNDECODED = frozenset(int(t) for t in UNDECODED_FEEDBACK_TYPES)
DOWN_POLL_S = 0.05  # a dead interface fails every receive at once: the thread waits this long between tries


class FeedbackReceiver(can.Listener):
    """Runs in the Notifier thread: keeps the latest valid feedback of each motor and notes bus trouble."""

    def __init__(self, can_ids: tuple[int, ...], clock: Callable[[], float]) -> None:
        self._slot = [-1] * 256
        for slot, can_id in enumerate(can_ids):
            self._slot[can_id] = slot
        self._clock = clock
        self.lock = threading.Lock()
        n = len(can_ids)
        self.raw = np.zeros((3, n))  # output position counts, velocity counts/s, phase current mA
        self.stamp = np.full((2, n), -np.inf)  # clock() of the last 0xB1 and 0xB2 per motor
        self.frames = 0  # every frame seen, ever
        self.reset()

    def reset(self) -> None:
        with self.lock:
            self.raw[:] = 0.0
            self.stamp[:] = -np.inf
        self.invalid_frames = 0
        self.undecoded_frames = 0  # 0xB0/0xB3 feedback: a Sito may send it; counted and ignored
        self.last_invalid_stamp = -np.inf
        self.last_invalid = ""
        self.bus_off = False
        self.down_error = ""

    def on_message_received(self, msg: can.Message) -> None:
        try:
            self._take(msg)
        finally:
            self.frames += 1  # counted once stored, so frames seen by a waiter are visible to read()

    def _take(self, msg: can.Message) -> None:
        ident = msg.arbitration_id
        if msg.is_error_frame:
            if ident & CAN_ERR_BUSOFF:
                self.bus_off = True
            return
        if not msg.is_extended_id or ident & ID_PREFIX_MASK != ID_PREFIX:
            return  # foreign traffic
        frame_type = ident & 0xFF
        data = msg.data
        problem = framing_problem(min(msg.dlc, len(data)), remote=msg.is_remote_frame, fd=msg.is_fd)
        if problem is not None:
            self._invalid(msg, problem)
            return
        if frame_type in _HOST_TYPES:
            return  # a host frame: our own echo or another tool on the bus
        if frame_type != _FEEDBACK1 and frame_type != _FEEDBACK2:
            if frame_type in _UNDECODED:
                self.undecoded_frames += 1
            else:
                self._invalid(msg, "unknown frame type")
            return
        slot = self._slot[(ident >> 8) & 0xFF]
        if slot < 0:
            return  # a Sito that is not ours
        now = self._clock()
        if frame_type == _FEEDBACK1:
            _, _, current, velocity = FEEDBACK1.unpack_from(data)
            with self.lock:
                self.raw[1, slot] = velocity
                self.raw[2, slot] = current
                self.stamp[0, slot] = now
        else:
            _, output = FEEDBACK2.unpack_from(data)
            with self.lock:
                self.raw[0, slot] = output
                self.stamp[1, slot] = now

    def _invalid(self, msg: can.Message, why: str) -> None:
        self.invalid_frames += 1
        self.last_invalid_stamp = self._clock()
        self.last_invalid = f"id 0x{msg.arbitration_id:08X} dlc {msg.dlc}: {why}"

    def on_error(self, exc: Exception) -> None:
        if is_interface_down(exc):
            self.down_error = str(exc) or type(exc).__name__
            time.sleep(DOWN_POLL_S)  # a dead interface fails every recv at once; do not spin
        else:
            self.invalid_frames += 1
            self.last_invalid_stamp = self._clock()
            self.last_invalid = f"undecodable frame: {exc}"
