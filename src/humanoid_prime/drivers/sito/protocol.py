"""Sito MIT-over-CAN wire format: SI <-> wire conversions and the packing and parsing of every frame type.

All frames are 29-bit extended with 8 big-endian data bytes (DESIGN §2):
``arbitration_id = 0x0506_0000 | (can_id << 8) | type``. Pure functions only; no bus here.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

ID_PREFIX = 0x0506_0000
ID_PREFIX_MASK = 0xFFFF_0000
DATA_LENGTH = 8

COUNTS_PER_RAD = 65536 / (2.0 * math.pi)  # position and velocity, output side
MODE_MIT = 0x09
FEEDBACK_INTERVAL_MS = range(0, 255)  # 0 = off, 1..254 ms
DISABLE_PAYLOAD = b"\x55" * DATA_LENGTH

INT16_MIN, INT16_MAX = -(2**15), 2**15 - 1
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1

# Payload layouts, each once: a NumPy dtype, and from it a struct for single frames. The host's per-tick packer
# (_tick.SitoTick) is built from HOST_PAYLOADS and MIT_FIELDS: which field carries each MIT command interface.
COMMAND_DTYPE = np.dtype([("current", ">i2"), ("velocity", ">i2"), ("position", ">i4")])  # mA, counts/s, counts
GAINS_DTYPE = np.dtype([("kp", ">f4"), ("kd", ">f4")])  # firmware units


def _frame_struct(payload: np.dtype[np.void]) -> struct.Struct:
    assert payload.names is not None  # a structured dtype
    return struct.Struct(">" + "".join(payload[f].char for f in payload.names))


COMMAND = _frame_struct(COMMAND_DTYPE)
GAINS = _frame_struct(GAINS_DTYPE)
HOST_PAYLOADS = np.dtype([("command", COMMAND_DTYPE), ("gains", GAINS_DTYPE)])  # one motor's, side by side
MIT_FIELDS = (("command", "position"), ("command", "velocity"), ("command", "current"), ("gains", "kp"),
              ("gains", "kd"))  # position, velocity, effort, stiffness, damping
ENABLE = struct.Struct(">BBBB4x")  # mode, feedback-1/2/3 interval ms
# 0xB1: voltage, pwm, phase current mA, velocity counts/s, as the peer's older Python and C++ drivers read it.
# Its newest (Rust) driver reads the phase current from bytes 2-3 (our pwm) instead, with no reason given
# (Berkeley-Humanoids/Actuator-Control, src/sito.rs); `prime can monitor` shows both readings, so a real
# motor settles it: the one that follows a known load is the current.
FEEDBACK1 = struct.Struct(">hhhh")
FEEDBACK2 = struct.Struct(">ii")  # motor position counts, output position counts


class FrameType(IntEnum):
    DISABLE = 0x00  # "reset", used as disable
    ENABLE = 0x01  # "select mode", used as enable
    COMMAND = 0x09
    GAINS = 0x45
    FEEDBACK0 = 0xB0  # a Sito may send it (the peer driver lists FEEDBACK_0); content undocumented
    FEEDBACK1 = 0xB1
    FEEDBACK2 = 0xB2
    FEEDBACK3 = 0xB3  # likewise (FEEDBACK_3; its interval is ENABLE's third byte, which Prime sends as 0)


HOST_FRAME_TYPES = frozenset({FrameType.DISABLE, FrameType.ENABLE, FrameType.COMMAND, FrameType.GAINS})
UNDECODED_FEEDBACK_TYPES = frozenset({FrameType.FEEDBACK0, FrameType.FEEDBACK3})  # counted, not decoded
MOTOR_FRAME_TYPES = frozenset({FrameType.FEEDBACK1, FrameType.FEEDBACK2, *UNDECODED_FEEDBACK_TYPES})


@dataclass(frozen=True)
class SitoModel:
    """Constants of one Sito model. ``kp_divisor``/``kd_divisor``: Nm/rad and Nm·s/rad per firmware unit."""

    name: str
    gear: float
    kt_nm_per_mA: float
    kp_divisor: float
    kd_divisor: float

    @property
    def nm_per_mA(self) -> float:
        """Output torque per mA of phase current."""
        return self.kt_nm_per_mA * self.gear


# Measured divisors 688.58 / 1.125 (DESIGN §2); the older 500 / 0.5 ran 1.38x too stiff, 2.25x over-damped.
SITO_MODELS: dict[str, SitoModel] = {
    "TA40-50": SitoModel("TA40-50", gear=51.0, kt_nm_per_mA=9e-5, kp_divisor=688.58, kd_divisor=1.125),
    "TA40-100": SitoModel("TA40-100", gear=101.0, kt_nm_per_mA=9e-5, kp_divisor=688.58, kd_divisor=1.125),
}


def sito_model(name: str) -> SitoModel:
    try:
        return SITO_MODELS[name]
    except KeyError:
        raise ValueError(f"unknown Sito model {name!r}; known models: {', '.join(SITO_MODELS)}") from None


class InvalidFrame(ValueError):
    """A frame in the Sito id range that breaks the protocol (unknown type, wrong length, bad payload)."""


# --- conversions -------------------------------------------------------------------------------------------

def _finite(value: float, what: str) -> float:
    if not math.isfinite(value):
        raise ValueError(f"{what} must be finite, got {value!r}")
    return value


def _clamp(value: int, low: int, high: int) -> tuple[int, bool]:
    if value < low:
        return low, True
    if value > high:
        return high, True
    return value, False


def position_to_counts(position: float) -> int:
    """Output position (rad) -> int32 counts, saturated at the int32 range."""
    return _clamp(round(_finite(position, "position") * COUNTS_PER_RAD), INT32_MIN, INT32_MAX)[0]


def counts_to_position(counts: int) -> float:
    return counts / COUNTS_PER_RAD


def velocity_to_counts(velocity: float) -> tuple[int, bool]:
    """Velocity (rad/s) -> int16 counts/s and whether it was clamped (int16 saturates near ±3.14 rad/s)."""
    return _clamp(round(_finite(velocity, "velocity") * COUNTS_PER_RAD), INT16_MIN, INT16_MAX)


def counts_to_velocity(counts: int) -> float:
    return counts / COUNTS_PER_RAD


def torque_to_current_mA(torque: float, model: SitoModel) -> tuple[int, bool]:
    """Feed-forward torque (Nm, output) -> int16 phase current (mA) and whether it was clamped."""
    return _clamp(round(_finite(torque, "torque") / model.nm_per_mA), INT16_MIN, INT16_MAX)


def current_mA_to_torque(current_mA: float, model: SitoModel) -> float:
    return current_mA * model.nm_per_mA


def wire_scales(model: SitoModel) -> npt.NDArray[np.float64]:
    """Wire units per SI unit of each MIT command interface, in ``MIT_FIELDS`` order: counts per rad, counts/s per
    rad/s, mA per Nm, firmware Kp per Nm/rad and firmware Kd per Nm*s/rad (the state's position, velocity and
    effort use the first three)."""
    return np.array([COUNTS_PER_RAD, COUNTS_PER_RAD, 1.0 / model.nm_per_mA, 1.0 / model.kp_divisor,
                     1.0 / model.kd_divisor])


def field_range(payload: str, field: str) -> tuple[float, float]:
    """The smallest and largest value a field of a host payload carries."""
    kind = HOST_PAYLOADS[payload][field]
    limits = np.finfo(kind) if kind.kind == "f" else np.iinfo(kind)
    return float(limits.min), float(limits.max)


def kp_to_firmware(kp: float, model: SitoModel) -> float:
    """Stiffness (Nm/rad) -> firmware Kp."""
    return kp / model.kp_divisor


def kd_to_firmware(kd: float, model: SitoModel) -> float:
    """Damping (Nm·s/rad) -> firmware Kd."""
    return kd / model.kd_divisor


def firmware_to_kp(kp_fw: float, model: SitoModel) -> float:
    """Firmware Kp -> the stiffness it realises at the joint (Nm/rad)."""
    return kp_fw * model.kp_divisor


def firmware_to_kd(kd_fw: float, model: SitoModel) -> float:
    return kd_fw * model.kd_divisor


# --- frames ------------------------------------------------------------------------------------------------

def arbitration_id(can_id: int, frame_type: int) -> int:
    if not 0 <= can_id <= 0xFF:
        raise ValueError(f"CAN id {can_id} out of range 0..255")
    if not 0 <= frame_type <= 0xFF:
        raise ValueError(f"frame type {frame_type} out of range 0..255")
    return ID_PREFIX | (can_id << 8) | frame_type


def split_arbitration_id(arbitration: int) -> tuple[int, int] | None:
    """(can_id, type) of an id in the Sito range, or None for foreign traffic."""
    if arbitration & ID_PREFIX_MASK != ID_PREFIX:
        return None
    return (arbitration >> 8) & 0xFF, arbitration & 0xFF


@dataclass(frozen=True)
class Disable:
    pass


@dataclass(frozen=True)
class Enable:
    mode: int
    feedback_ms: tuple[int, int, int]


@dataclass(frozen=True)
class Command:
    ff_current_mA: int
    velocity_counts: int
    position_counts: int


@dataclass(frozen=True)
class Gains:
    kp_fw: float
    kd_fw: float


@dataclass(frozen=True)
class Feedback1:
    voltage_raw: int
    pwm_raw: int
    phase_current_mA: int
    velocity_counts: int


@dataclass(frozen=True)
class Feedback2:
    motor_position_counts: int
    output_position_counts: int


@dataclass(frozen=True)
class UndecodedFeedback:
    """0xB0 or 0xB3: a feedback frame whose layout no source documents; kept as bytes."""

    frame_type: int
    data: bytes


Frame = Disable | Enable | Command | Gains | Feedback1 | Feedback2 | UndecodedFeedback

_TYPE_OF: dict[type, FrameType] = {
    Disable: FrameType.DISABLE, Enable: FrameType.ENABLE, Command: FrameType.COMMAND,
    Gains: FrameType.GAINS, Feedback1: FrameType.FEEDBACK1, Feedback2: FrameType.FEEDBACK2,
}


def pack(frame: Frame) -> tuple[int, bytes]:
    """(type, 8 data bytes) of ``frame``; ValueError if a field does not fit its wire type."""
    try:
        match frame:
            case Disable():
                data = DISABLE_PAYLOAD
            case Enable(mode, feedback_ms):
                if len(feedback_ms) != 3 or any(ms not in FEEDBACK_INTERVAL_MS for ms in feedback_ms):
                    raise ValueError(f"feedback intervals must be three values in 0..254 ms, got {feedback_ms}")
                data = ENABLE.pack(mode, *feedback_ms)
            case Command(ff, velocity, position):
                data = COMMAND.pack(ff, velocity, position)
            case Gains(kp_fw, kd_fw):
                data = GAINS.pack(kp_fw, kd_fw)
            case Feedback1(voltage, pwm, current, velocity):
                data = FEEDBACK1.pack(voltage, pwm, current, velocity)
            case Feedback2(motor, output):
                data = FEEDBACK2.pack(motor, output)
            case UndecodedFeedback(frame_type, payload):
                if frame_type not in UNDECODED_FEEDBACK_TYPES or len(payload) != DATA_LENGTH:
                    raise ValueError(f"{frame!r} is not an 8-byte 0xB0/0xB3 frame")
                return frame_type, bytes(payload)
            case _:
                raise TypeError(f"not a Sito frame: {frame!r}")
    except struct.error as exc:
        raise ValueError(f"{frame!r} does not fit the wire format: {exc}") from None
    return _TYPE_OF[type(frame)], data


def pack_frame(can_id: int, frame: Frame) -> tuple[int, bytes]:
    """(arbitration id, data) of ``frame`` addressed to ``can_id``."""
    frame_type, data = pack(frame)
    return arbitration_id(can_id, frame_type), data


def framing_problem(data_length: int, *, remote: bool = False, fd: bool = False) -> str | None:
    """Why a frame in the Sito id range cannot be a Sito frame, whatever its type (None: it can be, and ``parse``
    reads its payload): every Sito frame is a classic CAN data frame of DATA_LENGTH bytes. ``data_length``: the
    bytes it carries (of a python-can message, ``min(dlc, len(data))``)."""
    if remote:
        return "a remote frame; every Sito frame is a data frame"
    if fd:
        return "a CAN FD frame; every Sito frame is classic CAN"
    if data_length != DATA_LENGTH:
        return f"{data_length} data bytes, every Sito frame has {DATA_LENGTH}"
    return None


def parse(frame_type: int, data: bytes | bytearray, *, remote: bool = False, fd: bool = False) -> Frame:
    """Decode a frame of ``frame_type`` carrying ``data`` (``remote``, ``fd``: what kind of CAN frame it came in);
    InvalidFrame if it breaks the protocol."""
    problem = framing_problem(len(data), remote=remote, fd=fd)
    if problem is not None:
        raise InvalidFrame(problem)
    match frame_type:
        case FrameType.FEEDBACK1:
            return Feedback1(*FEEDBACK1.unpack(data))
        case FrameType.FEEDBACK2:
            return Feedback2(*FEEDBACK2.unpack(data))
        case FrameType.FEEDBACK0 | FrameType.FEEDBACK3:
            return UndecodedFeedback(frame_type, bytes(data))
        case FrameType.COMMAND:
            return Command(*COMMAND.unpack(data))
        case FrameType.GAINS:
            kp_fw, kd_fw = GAINS.unpack(data)
            if not (math.isfinite(kp_fw) and math.isfinite(kd_fw)):
                raise InvalidFrame(f"non-finite gains Kp={kp_fw} Kd={kd_fw}")
            return Gains(kp_fw, kd_fw)
        case FrameType.ENABLE:
            if any(data[4:]):
                raise InvalidFrame("select-mode frame with non-zero reserved bytes 4..7")
            mode, fb1, fb2, fb3 = ENABLE.unpack(data)
            if any(ms not in FEEDBACK_INTERVAL_MS for ms in (fb1, fb2, fb3)):
                raise InvalidFrame(f"feedback interval above 254 ms: {fb1}, {fb2}, {fb3}")
            return Enable(mode, (fb1, fb2, fb3))
        case FrameType.DISABLE:
            if bytes(data) != DISABLE_PAYLOAD:
                raise InvalidFrame("reset frame whose payload is not eight 0x55 bytes")
            return Disable()
    raise InvalidFrame(f"unknown frame type 0x{frame_type:02X}")


def parse_frame(arbitration: int, data: bytes | bytearray) -> tuple[int, Frame]:
    """(can_id, frame) of a frame in the Sito id range; InvalidFrame otherwise."""
    split = split_arbitration_id(arbitration)
    if split is None:
        raise InvalidFrame(f"id 0x{arbitration:08X} is outside the Sito range 0x0506xxxx")
    can_id, frame_type = split
    return can_id, parse(frame_type, data)
