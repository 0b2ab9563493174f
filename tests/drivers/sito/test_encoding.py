"""The compiled packer writes protocol's wire format: any double in any command interface gives payloads that
protocol parses, within their types, equal to protocol's own conversions where those fit and saturated where
they do not; a command its fields cannot carry goes out limp. Over the full float range, infinities and NaN."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from humanoid_prime.drivers.sito._tick import INVALID, SitoTick  # private to the package: the compiled kernel
from humanoid_prime.drivers.sito.protocol import (
    HOST_PAYLOADS,
    INT16_MAX,
    INT16_MIN,
    INT32_MAX,
    INT32_MIN,
    MIT_FIELDS,
    SITO_MODELS,
    Command,
    FrameType,
    Gains,
    kd_to_firmware,
    kp_to_firmware,
    parse,
    wire_scales,
)

MODEL = SITO_MODELS["TA40-50"]
SCALES = wire_scales(MODEL)
SCALE = [float(scale) for scale in SCALES]  # Python floats: a product beyond the doubles is inf, no warning
FLOAT32_MAX = float(np.finfo(np.float32).max)
any_double = st.floats(allow_nan=True, allow_infinity=True)
interface = st.one_of(any_double, st.floats(-10.0, 10.0), st.sampled_from([0.0, -0.0, math.nan]))


def packer(direction: float, offset: float) -> tuple[SitoTick, np.ndarray]:
    """A one-motor packer with a calibration, and the robot command it packs from (5 x 1)."""
    sign = np.array([[direction], [direction], [direction], [1.0], [1.0]])
    tick = SitoTick(np.zeros(1, dtype=np.intp), SCALES[:, None] * sign, np.array([offset * SCALES[0]]),
                    np.zeros((3, 1)), np.zeros((2, 1)), HOST_PAYLOADS, MIT_FIELDS)
    return tick, np.zeros((5, 1))


def saturated(exact: float, low: int, high: int) -> int:
    return low if exact < low else high if exact > high else round(exact)


@settings(max_examples=600, deadline=None)
@given(values=st.tuples(*[interface] * 5), direction=st.sampled_from([1.0, -1.0]),
       offset=st.floats(-math.pi, math.pi))
@example(values=(1e308, 1e6, 0.0, 1e9, 1e9), direction=1.0, offset=0.0)  # the REMOTE values of DESIGN's case
@example(values=(1.7e308, 0.0, 0.0, 0.0, 0.0), direction=-1.0, offset=0.5)  # a limp target beyond int32
@example(values=(0.0, 0.0, 0.0, 3e41, 0.0), direction=1.0, offset=0.0)  # Kp beyond float32
def test_every_command_packs_into_fields_protocol_parses_without_overflow(values, direction, offset):
    tick, command = packer(direction, offset)
    command[:, 0] = values
    tick.write(command, -math.inf)
    payloads = bytes(tick.payloads.view(np.uint8))
    sent = parse(FrameType.COMMAND, payloads[:8])
    gains = parse(FrameType.GAINS, payloads[8:])  # InvalidFrame if a gain went out non-finite
    assert isinstance(sent, Command) and isinstance(gains, Gains)
    assert gains.kp_fw >= 0.0 and gains.kd_fw >= 0.0

    position, velocity, effort, kp, kd = values
    usable = (all(math.isfinite(v) for v in values) and kp >= 0.0 and kd >= 0.0
              and kp_to_firmware(kp, MODEL) <= FLOAT32_MAX and kd_to_firmware(kd, MODEL) <= FLOAT32_MAX)
    no_command = math.isnan(position) and velocity == effort == kp == kd == 0.0
    assert tick.problems[INVALID, 0] == (not usable and not no_command)
    if not usable:  # limp: no gains, no effort, the target on the offset
        position = velocity = effort = kp = kd = 0.0
    exact = ((direction * position + offset) * SCALE[0], direction * velocity * SCALE[1],
             direction * effort * SCALE[2])
    got = (sent.position_counts, sent.velocity_counts, sent.ff_current_mA)
    ranges = ((INT32_MIN, INT32_MAX), (INT16_MIN, INT16_MAX), (INT16_MIN, INT16_MAX))
    for row, (g, x, (low, high)) in enumerate(zip(got, exact, ranges, strict=True)):
        # one count of slack where the offset is added in counts (packer) or in rad (here) before rounding
        assert abs(g - saturated(x, low, high)) <= (1 if row == 0 else 0), (row, g, x)
        if not low - 1 <= x <= high + 1:
            assert tick.problems[row, 0], f"row {row} saturated unflagged"
        elif low + 1 <= x <= high - 1:
            assert not tick.problems[row, 0], f"row {row} flagged within range"
    assert gains.kp_fw == np.float32(kp_to_firmware(kp, MODEL)) or math.isclose(
        gains.kp_fw, kp_to_firmware(kp, MODEL), rel_tol=1e-6)
    assert gains.kd_fw == np.float32(kd_to_firmware(kd, MODEL)) or math.isclose(
        gains.kd_fw, kd_to_firmware(kd, MODEL), rel_tol=1e-6)


def test_the_packer_refuses_a_layout_it_cannot_write():
    little = np.dtype([("command", [("current", "<i2"), ("velocity", ">i2"), ("position", ">i4")]),
                       ("gains", HOST_PAYLOADS["gains"])])
    try:
        SitoTick(np.zeros(1, dtype=np.intp), np.ones((5, 1)), np.zeros(1), np.zeros((3, 1)), np.zeros((2, 1)),
                 little, MIT_FIELDS)
    except ValueError as exc:
        assert "command.current is <i2" in str(exc)
    else:
        raise AssertionError("a little-endian field was accepted")


def test_the_packer_follows_the_layout_protocol_gives_it():
    """Fields in another order land where the layout says: the packer holds no offsets of its own."""
    swapped = np.dtype([("gains", HOST_PAYLOADS["gains"]),
                        ("command", [("position", ">i4"), ("current", ">i2"), ("velocity", ">i2")])])
    tick = SitoTick(np.zeros(1, dtype=np.intp), SCALES[:, None] * np.ones((5, 1)), np.zeros(1), np.zeros((3, 1)),
                    np.zeros((2, 1)), swapped, MIT_FIELDS)
    tick.write(np.array([[1.0], [0.5], [0.459], [688.58], [2.25]]), -math.inf)
    assert bytes(tick.payloads.view(np.uint8)).hex() == "3f80000040000000" + "000028be" + "0064" + "145f"
