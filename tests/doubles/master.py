"""A test double of the master interface: a recorded process image and ten CiA402 drives, no network.

Each drive follows the controlword through the CiA402 states (one step per frame), reports the mode it
was asked for, and reads back whatever position the test sets. Slaves reach OP a few frames after OP is
requested, so the base class's bring-up loop runs for real.
"""

from __future__ import annotations

import struct
import sys
from collections.abc import Sequence

import numpy as np

from humanoid_prime.drivers.erob.constants import PRODUCT_CODE, VENDOR_ID
from humanoid_prime.drivers.ethercat.errors import SdoError
from humanoid_prime.drivers.ethercat.master import RX_DTYPE, TX_DTYPE, EthercatMaster
from humanoid_prime.drivers.ethercat.ring import SlaveInfo
from humanoid_prime.drivers.ethercat.wire import AlState

SWITCH_ON_DISABLED = 0x0250
READY_TO_SWITCH_ON = 0x0231
SWITCHED_ON = 0x0233
OPERATION_ENABLED = 0x1637  # 5687
FAULT = 0x1208  # 4616


def erob_ring(n: int = 10) -> list[SlaveInfo]:
    return [SlaveInfo(k, "eRob", VENDOR_ID, PRODUCT_CODE, 1, AlState.PRE_OP) for k in range(n)]


class FakeMaster(EthercatMaster):
    def __init__(self, slaves: Sequence[SlaveInfo] | None = None, *, update_rate: float = 50.0,
                 bringup_rate: float = 1000.0, op_after_frames: int = 3, input_dtype: np.dtype = TX_DTYPE,
                 **options) -> None:
        super().__init__("fake0", update_rate=update_rate, bringup_rate=bringup_rate, **options)
        self.found = list(slaves) if slaves is not None else erob_ring()
        n = len(self.found)
        self.op_after_frames = op_after_frames
        self.input_dtype = input_dtype  # the process image's inputs as this master lays them out
        self.states = [AlState.PRE_OP] * n
        self.frames = 0
        self._op_requested_at: int | None = None
        self.position_counts = np.zeros(n, dtype=np.int64)
        self.velocity_counts = np.zeros(n, dtype=np.int64)
        self.torque_per_mille = np.zeros(n, dtype=np.int64)
        self.statusword = np.full(n, SWITCH_ON_DISABLED, dtype=np.int64)
        self.error_code = np.zeros(n, dtype=np.int64)
        self.sent = np.zeros(n, RX_DTYPE)  # the outputs of the last frame, as the drives got them
        self.wkc_override: int | None = None
        self.drives_follow = True  # False: the drives ignore every controlword (a drive that refuses to enable)
        self.rated_torque_mnm: list[int | None] = [23000] * n  # what each drive's 0x6076 answers (None: no reply)
        self.objects: dict[tuple[int, int, int], bytes] = {}
        self.sdo_log: list[tuple[str, int, int, int]] = []
        self.closed = False
        self._prev_cw = np.zeros(n, dtype=np.int64)
        self.switch_interval_at_op: list[float] = []  # the interpreter's switch interval at each request for OP

    def _discover(self) -> Sequence[SlaveInfo]:
        return self.found

    def _configure(self) -> None:
        n = len(self.found)
        self.outputs = np.zeros(n, RX_DTYPE)
        self.inputs = np.zeros(n, self.input_dtype)
        self.expected_wkc = 3 * n
        self.states = [AlState.SAFE_OP] * n
        for k, milli in enumerate(self.rated_torque_mnm):  # read in PRE-OP, as SoemMaster does
            if milli is None:
                self.rated_torque_problems[k] = "no reply (working counter 0)"
            else:
                self.store_rated_torque(k, struct.pack("<I", milli))

    def _request_op(self) -> None:
        self.switch_interval_at_op.append(sys.getswitchinterval())
        self._op_requested_at = self.frames

    def _read_states(self) -> list[tuple[int, int]]:
        return [(s, 0) for s in self.states]

    def _advance(self, states) -> None:
        pass

    def _send(self) -> None:
        np.copyto(self.sent, self.outputs)
        self.frames += 1
        if self._op_requested_at is not None and self.frames - self._op_requested_at >= self.op_after_frames:
            self.states = [AlState.OP if s == AlState.SAFE_OP else s for s in self.states]
        if all(s == AlState.OP for s in self.states) and self.drives_follow:
            self._step_drives(self.sent["controlword"].astype(np.int64))

    def _step_drives(self, cw: np.ndarray) -> None:
        for k in range(len(cw)):
            sw, c = int(self.statusword[k]), int(cw[k])
            if sw == FAULT:
                if c & 0x80 and not self._prev_cw[k] & 0x80:
                    self.statusword[k] = SWITCH_ON_DISABLED
                    self.error_code[k] = 0
            elif c & 0x87 == 0x06:
                self.statusword[k] = READY_TO_SWITCH_ON
            elif c & 0x8F == 0x07 and sw in (READY_TO_SWITCH_ON, OPERATION_ENABLED):
                self.statusword[k] = SWITCHED_ON
            elif c & 0x8F == 0x0F and sw in (SWITCHED_ON, OPERATION_ENABLED):
                self.statusword[k] = OPERATION_ENABLED
            elif c & 0x82 == 0x00:
                self.statusword[k] = SWITCH_ON_DISABLED
        np.copyto(self._prev_cw, cw)

    def _receive(self) -> int:
        inputs = self.inputs
        inputs["statusword"] = self.statusword
        inputs["position_actual"] = self.position_counts
        inputs["velocity_actual"] = self.velocity_counts
        inputs["torque_actual"] = self.torque_per_mille
        inputs["error_code"] = self.error_code
        inputs["mode_display"] = self.sent["mode_of_operation"]
        return self.expected_wkc if self.wkc_override is None else self.wkc_override

    def fault(self, position: int, error_code: int) -> None:
        self.statusword[position] = FAULT
        self.error_code[position] = error_code

    def _sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        self.sdo_log.append(("read", position, index, sub_index))
        try:
            return self.objects[(position, index, sub_index)]
        except KeyError:
            raise SdoError(position, index, sub_index, "aborted with 0x06020000 (object does not exist)",
                           0x06020000) from None

    def _sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        self.sdo_log.append(("write", position, index, sub_index))
        self.objects[(position, index, sub_index)] = data

    def _close(self) -> None:
        self.closed = True


def u32(value: int) -> bytes:
    return struct.pack("<I", value)


class MirrorMaster(EthercatMaster):
    """A ring that reports, frame by frame, whatever inputs the test gives it (``feed``, set before each read) and
    keeps the outputs of the last frame (``sent``): a host component on it sees exactly what another saw."""

    def __init__(self, feed: np.ndarray, *, rated_torque_mnm: int, update_rate: float = 50.0) -> None:
        super().__init__("mirror0", update_rate=update_rate)
        self.feed = feed.copy()
        self.sent = np.zeros(len(feed), RX_DTYPE)
        self._rated = rated_torque_mnm

    def _discover(self) -> Sequence[SlaveInfo]:
        return erob_ring(len(self.feed))

    def _configure(self) -> None:
        n = len(self.feed)
        self.outputs, self.inputs = np.zeros(n, RX_DTYPE), np.zeros(n, TX_DTYPE)
        self.expected_wkc = 3 * n
        for k in range(n):
            self.store_rated_torque(k, u32(self._rated))

    def _request_op(self) -> None:
        pass

    def _read_states(self) -> list[tuple[int, int]]:
        return [(AlState.OP, 0)] * len(self.feed)

    def _advance(self, states) -> None:
        pass

    def _send(self) -> None:
        np.copyto(self.sent, self.outputs)

    def _receive(self) -> int:
        np.copyto(self.inputs, self.feed)
        return self.expected_wkc

    def _sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        raise SdoError(position, index, sub_index, "the mirror ring has no mailbox")

    def _sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        raise SdoError(position, index, sub_index, "the mirror ring has no mailbox")

    def _close(self) -> None:
        pass
