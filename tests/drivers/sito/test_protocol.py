"""The Sito wire format and SI conversions, against the numbers in DESIGN §2."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from humanoid_prime.drivers.sito.protocol import (
    COUNTS_PER_RAD,
    MOTOR_FRAME_TYPES,
    SITO_MODELS,
    Command,
    Disable,
    Enable,
    Feedback1,
    Feedback2,
    FrameType,
    Gains,
    InvalidFrame,
    UndecodedFeedback,
    arbitration_id,
    counts_to_position,
    counts_to_velocity,
    current_mA_to_torque,
    firmware_to_kd,
    firmware_to_kp,
    framing_problem,
    kd_to_firmware,
    kp_to_firmware,
    pack,
    pack_frame,
    parse,
    parse_frame,
    position_to_counts,
    sito_model,
    split_arbitration_id,
    torque_to_current_mA,
    velocity_to_counts,
)

TA40_50 = SITO_MODELS["TA40-50"]
ONE_COUNT = 1.0 / COUNTS_PER_RAD
int16 = st.integers(-(2**15), 2**15 - 1)
int32 = st.integers(-(2**31), 2**31 - 1)
interval = st.integers(0, 254)


def test_ta40_50_constants():
    assert (TA40_50.gear, TA40_50.kt_nm_per_mA, TA40_50.kp_divisor, TA40_50.kd_divisor) == (51.0, 9e-5, 688.58, 1.125)


def test_ta40_100_gear_is_101():
    assert SITO_MODELS["TA40-100"].gear == 101.0


def test_unknown_model_names_the_known_ones():
    with pytest.raises(ValueError, match="TA40-50"):
        sito_model("TA99")


def test_counts_per_rad_is_65536_over_two_pi():
    assert abs(COUNTS_PER_RAD - 10430.378350470453) < 1e-9


def test_arbitration_id_layout():
    assert arbitration_id(22, FrameType.COMMAND) == 0x05061609
    assert arbitration_id(0x27, FrameType.FEEDBACK2) == 0x050627B2


def test_split_arbitration_id_rejects_foreign_ids():
    assert split_arbitration_id(0x050616B1) == (22, 0xB1)
    assert split_arbitration_id(0x05071609) is None


def test_one_rad_is_10430_counts():
    assert position_to_counts(1.0) == 10430


def test_feed_forward_current_is_torque_over_kt_times_gear():
    assert torque_to_current_mA(0.459, TA40_50) == (100, False)


def test_state_torque_is_current_times_kt_times_gear():
    assert current_mA_to_torque(1000, TA40_50) == pytest.approx(4.59)


def test_measured_divisors():
    assert kp_to_firmware(688.58, TA40_50) == 1.0
    assert kd_to_firmware(1.125, TA40_50) == 1.0


def test_old_divisors_were_1_38x_too_stiff_and_2_25x_over_damped():
    kp, kd = 20.0, 2.0
    realised_kp = firmware_to_kp(kp / 500.0, TA40_50)
    realised_kd = firmware_to_kd(kd / 0.5, TA40_50)
    assert round(realised_kp / kp, 2) == 1.38
    assert realised_kd / kd == pytest.approx(2.25)


def test_velocity_beyond_int16_is_clamped_and_reported():
    assert velocity_to_counts(10.0) == (32767, True)
    assert velocity_to_counts(-10.0) == (-32768, True)


def test_velocity_saturates_near_pi_rad_per_s():
    assert counts_to_velocity(32767) == pytest.approx(3.1415, abs=1e-4)


def test_velocity_within_range_is_not_reported():
    assert velocity_to_counts(3.14) == (32751, False)


def test_non_finite_values_are_refused():
    with pytest.raises(ValueError, match="finite"):
        position_to_counts(math.nan)


# --- exact bytes ------------------------------------------------------------------------------------------

def test_command_bytes():
    assert pack_frame(22, Command(100, 5215, 10430)) == (0x05061609, bytes.fromhex("0064145f000028be"))


def test_gains_bytes_for_one_firmware_unit_each():
    ident, data = pack_frame(22, Gains(kp_to_firmware(688.58, TA40_50), kd_to_firmware(2.25, TA40_50)))
    assert (ident, data) == (0x05061645, bytes.fromhex("3f80000040000000"))


def test_gains_bytes_for_standby():
    _, data = pack_frame(22, Gains(kp_to_firmware(20.0, TA40_50), kd_to_firmware(2.0, TA40_50)))
    assert data == bytes.fromhex("3cedf05f3fe38e39")


def test_enable_bytes_at_50_hz():
    assert pack_frame(38, Enable(0x09, (20, 20, 0))) == (0x05062601, bytes.fromhex("0914140000000000"))


def test_disable_is_eight_0x55():
    assert pack_frame(39, Disable()) == (0x05062700, b"\x55" * 8)


def test_feedback1_bytes():
    assert pack(Feedback1(240, -12, 100, -5215)) == (0xB1, bytes.fromhex("00f0fff40064eba1"))


def test_feedback2_bytes():
    assert pack(Feedback2(531930, -1043)) == (0xB2, bytes.fromhex("00081dda fffffbed"))


def test_parse_feedback2():
    assert parse_frame(0x050617B2, bytes.fromhex("00000001000028be")) == (23, Feedback2(1, 10430))


def test_parse_refuses_wrong_length():
    with pytest.raises(InvalidFrame, match="5 data bytes"):
        parse(0xB2, bytes(5))


@pytest.mark.parametrize("length, kind, says", [
    (3, {}, "3 data bytes, every Sito frame has 8"),
    (64, {"fd": True}, "a CAN FD frame"),
    (8, {"fd": True}, "a CAN FD frame"),
    (0, {"remote": True}, "a remote frame"),
])
def test_a_frame_that_is_no_classic_8_byte_data_frame_is_invalid_whatever_its_type(length, kind, says):
    assert framing_problem(length, **kind).startswith(says)
    with pytest.raises(InvalidFrame, match=says):
        parse(0xB2, bytes(length), **kind)


def test_a_classic_8_byte_data_frame_is_left_to_its_type_to_judge():
    assert framing_problem(8) is None


@pytest.mark.parametrize("frame_type", [0xB0, 0xB3])
def test_feedback_0_and_3_parse_as_undecoded_frames(frame_type):
    data = bytes(range(8))
    assert parse(frame_type, data) == UndecodedFeedback(frame_type, data)
    assert pack(UndecodedFeedback(frame_type, data)) == (frame_type, data)
    assert frame_type in MOTOR_FRAME_TYPES


def test_undecoded_feedback_packs_only_as_0xb0_or_0xb3():
    with pytest.raises(ValueError, match="0xB0/0xB3"):
        pack(UndecodedFeedback(0xB1, bytes(8)))


def test_parse_refuses_unknown_type():
    with pytest.raises(InvalidFrame, match="0xB7"):
        parse(0xB7, bytes(8))


def test_parse_refuses_a_reset_without_0x55():
    with pytest.raises(InvalidFrame):
        parse(0x00, bytes(8))


def test_parse_refuses_nan_gains():
    with pytest.raises(InvalidFrame):
        parse(0x45, struct.pack(">ff", math.nan, 1.0))


def test_pack_refuses_a_field_that_does_not_fit():
    with pytest.raises(ValueError):
        pack(Command(40000, 0, 0))


def test_pack_refuses_interval_above_254():
    with pytest.raises(ValueError, match="254"):
        pack(Enable(0x09, (255, 20, 0)))


# --- properties ---------------------------------------------------------------------------------------------

@given(st.floats(-1000.0, 1000.0))
def test_position_round_trip_within_one_count(q):
    assert abs(counts_to_position(position_to_counts(q)) - q) <= ONE_COUNT


@given(st.floats(-3.14, 3.14))
def test_velocity_round_trip_within_one_count(qd):
    counts, clamped = velocity_to_counts(qd)
    assert not clamped
    assert abs(counts_to_velocity(counts) - qd) <= ONE_COUNT


@given(st.floats(-100.0, 100.0))
def test_effort_round_trip_within_one_milliamp(tau):
    current, clamped = torque_to_current_mA(tau, TA40_50)
    assert not clamped
    assert abs(current_mA_to_torque(current, TA40_50) - tau) <= TA40_50.nm_per_mA


@given(st.floats(0.0, 1000.0), st.floats(0.0, 100.0))
def test_gains_round_trip_through_float32(kp, kd):
    kp_fw, kd_fw = struct.unpack(">ff", pack(Gains(kp_to_firmware(kp, TA40_50), kd_to_firmware(kd, TA40_50)))[1])
    assert firmware_to_kp(kp_fw, TA40_50) == pytest.approx(kp, rel=1e-6, abs=1e-12)
    assert firmware_to_kd(kd_fw, TA40_50) == pytest.approx(kd, rel=1e-6, abs=1e-12)


@given(int16, int16, int32)
def test_command_frame_round_trip(current, velocity, position):
    frame = Command(current, velocity, position)
    assert parse(*pack(frame)) == frame


@given(int16, int16, int16, int16)
def test_feedback1_frame_round_trip(voltage, pwm, current, velocity):
    frame = Feedback1(voltage, pwm, current, velocity)
    assert parse(*pack(frame)) == frame


@given(int32, int32)
def test_feedback2_frame_round_trip(motor, output):
    frame = Feedback2(motor, output)
    assert parse(*pack(frame)) == frame


@given(st.integers(0, 255), interval, interval, interval)
def test_enable_frame_round_trip(mode, fb1, fb2, fb3):
    frame = Enable(mode, (fb1, fb2, fb3))
    assert parse(*pack(frame)) == frame


@given(st.floats(width=32, allow_nan=False, allow_infinity=False),
       st.floats(width=32, allow_nan=False, allow_infinity=False))
def test_gains_frame_round_trip(kp_fw, kd_fw):
    frame = Gains(kp_fw, kd_fw)
    assert parse(*pack(frame)) == frame


def test_disable_frame_round_trip():
    assert parse(*pack(Disable())) == Disable()
