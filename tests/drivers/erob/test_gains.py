"""eRob SI <-> register conversion and the never-stiffer write order (DESIGN §2)."""

import itertools
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from humanoid_prime.config.hardware import DEFAULT_GEAR, DEFAULT_KT_NM_PER_MA
from humanoid_prime.drivers.erob.constants import EROB80_KT_NM_PER_MA
from humanoid_prime.drivers.erob.gains import (
    REGISTER_MAX,
    ErobRegisters,
    gains_to_registers,
    pos_reg_exact,
    registers_to_gains,
    vel_reg_exact,
    write_order,
)
from humanoid_prime.drivers.erob.objects import POS_LOOP_GAIN, VEL_LOOP_GAIN, VEL_LOOP_INTEGRAL


def test_standby_vel_reg_before_rounding():
    assert vel_reg_exact(2.0) == pytest.approx(18.8147, abs=1e-4)  # 2 / 0.1063


def test_standby_pos_reg_before_rounding():
    assert pos_reg_exact(20.0, 2.0) == pytest.approx(514.7)  # (20 / 2) * 51.47


def test_standby_registers_round_to_nearest():
    assert gains_to_registers(20.0, 2.0) == ErobRegisters(pos_reg=515, vel_reg=19, integral=0)


def test_damping_mode_has_zero_position_gain():
    regs = gains_to_registers(0.0, 6.0)
    assert regs.pos_reg == 0
    assert regs.vel_reg == round(6.0 / 0.1063) == 56


def test_zero_torque_is_all_zero():
    assert gains_to_registers(0.0, 0.0) == ErobRegisters(0, 0, 0)


def test_kd_zero_gives_zero_position_register_exactly():
    assert pos_reg_exact(20.0, 0.0) == 0.0


def test_erob80_kt_gives_vel_reg_1_5_percent_lower():
    ratio = vel_reg_exact(2.0, kt=EROB80_KT_NM_PER_MA) / vel_reg_exact(2.0)
    assert ratio == pytest.approx(0.132 / 0.134)
    assert (1 - ratio) * 100 == pytest.approx(1.49, abs=0.01)


def test_kt_and_gear_scale_only_vel_reg():
    a = gains_to_registers(20.0, 6.0)
    b = gains_to_registers(20.0, 6.0, kt=DEFAULT_KT_NM_PER_MA, gear=2 * DEFAULT_GEAR)
    assert b.pos_reg == a.pos_reg
    assert b.vel_reg == round(vel_reg_exact(6.0) / 2)


def test_efficiency_divides_only_vel_reg():
    a = gains_to_registers(20.0, 6.0)
    b = gains_to_registers(20.0, 6.0, efficiency=0.7)
    assert b.pos_reg == a.pos_reg
    assert vel_reg_exact(6.0, efficiency=0.7) == pytest.approx(vel_reg_exact(6.0) / 0.7)


def test_efficiency_restores_realised_gains_on_a_lossy_drive():
    regs = gains_to_registers(20.0, 6.0, efficiency=0.7)
    kp, kd = registers_to_gains(regs, transmission_efficiency=0.7)
    assert kd == pytest.approx(6.0, rel=0.01)
    assert kp == pytest.approx(20.0, rel=0.01)


def test_uncompensated_drive_realises_seventy_percent():
    regs = gains_to_registers(20.0, 6.0)
    kp_nominal, kd_nominal = registers_to_gains(regs)
    kp, kd = registers_to_gains(regs, transmission_efficiency=0.7)
    assert (kp / kp_nominal, kd / kd_nominal) == pytest.approx((0.7, 0.7))


def test_standby_registers_realise_the_rounded_gains():
    kp, kd = registers_to_gains(ErobRegisters(pos_reg=515, vel_reg=19, integral=0))
    assert kd == pytest.approx(19 * 0.1063)
    assert kp == pytest.approx(515 / 51.47 * 19 * 0.1063)


def test_stiffness_without_damping_is_refused():
    with pytest.raises(ValueError, match="stiffness needs damping"):
        gains_to_registers(20.0, 0.0)


@pytest.mark.parametrize("kp, kd", [(-1.0, 2.0), (20.0, -2.0), (math.nan, 2.0), (20.0, math.inf)])
def test_negative_or_non_finite_gains_are_refused(kp, kd):
    with pytest.raises(ValueError, match="finite number >= 0"):
        gains_to_registers(kp, kd)


def test_damping_beyond_u16_is_refused():
    with pytest.raises(ValueError, match="does not fit the u16 register"):
        gains_to_registers(0.0, (REGISTER_MAX + 1) * 0.1063)


def test_stiffness_ratio_beyond_u16_is_refused():
    with pytest.raises(ValueError, match="pos_reg .* does not fit"):
        gains_to_registers(1e5, 0.1063)


def test_damping_below_one_step_is_refused():
    with pytest.raises(ValueError, match="rounds to vel_reg 0"):
        gains_to_registers(0.0, 0.01)


@pytest.mark.parametrize("efficiency", [0.0, 1.2, math.nan])
def test_efficiency_outside_zero_one_is_refused(efficiency):
    with pytest.raises(ValueError, match="efficiency"):
        gains_to_registers(20.0, 2.0, efficiency=efficiency)


@given(kp=st.floats(0.0, 300.0), kd=st.floats(0.5, 50.0), efficiency=st.floats(0.5, 1.0))
def test_realised_gains_match_the_request_within_one_register_step(kp, kd, efficiency):
    regs = gains_to_registers(kp, kd, efficiency=efficiency)
    real_kp, real_kd = registers_to_gains(regs, transmission_efficiency=efficiency)
    assert abs(real_kd - kd) <= 0.1063 / 2 + 1e-9  # half a vel_reg step
    assert abs(real_kp / real_kd - kp / kd) <= 0.5 / 51.47 + 1e-9  # half a pos_reg step of the ratio


# write order --------------------------------------------------------------------------------------------------

def test_first_write_sends_all_three_integral_first():
    writes = write_order(None, ErobRegisters(515, 19, 0))
    assert writes[0] == (VEL_LOOP_INTEGRAL, 0)
    assert sorted(writes) == sorted([(VEL_LOOP_INTEGRAL, 0), (POS_LOOP_GAIN, 515), (VEL_LOOP_GAIN, 19)])


def test_unchanged_registers_are_not_written():
    assert write_order(ErobRegisters(515, 19, 0), ErobRegisters(515, 19, 0)) == []
    assert write_order(ErobRegisters(515, 19, 0), ErobRegisters(0, 19, 0)) == [(POS_LOOP_GAIN, 0)]


def test_falling_damping_writes_vel_reg_first():
    # STANDBY (20, 2) -> ZERO_TORQUE: damping falls
    assert write_order(ErobRegisters(515, 19, 0), ErobRegisters(0, 0, 0)) == [(VEL_LOOP_GAIN, 0), (POS_LOOP_GAIN, 0)]


def test_rising_damping_writes_pos_reg_first():
    # STANDBY (20, 2) -> DAMPING (0, 6): damping rises
    assert write_order(ErobRegisters(515, 19, 0), ErobRegisters(0, 56, 0)) == [(POS_LOOP_GAIN, 0), (VEL_LOOP_GAIN, 56)]


def test_integral_is_written_first():
    writes = write_order(ErobRegisters(515, 19, 7), ErobRegisters(0, 56, 0))
    assert writes[0] == (VEL_LOOP_INTEGRAL, 0)


def _gains(pos: int, vel: int) -> tuple[int, int]:
    return pos * vel, vel  # kp and kd in register units


def test_no_intermediate_state_is_stiffer_or_more_damped_than_both_ends():
    values = [0, 1, 2, 19, 56, 515, 1000]
    for old_pos, old_vel, new_pos, new_vel in itertools.product(values, repeat=4):
        old, new = ErobRegisters(old_pos, old_vel, 0), ErobRegisters(new_pos, new_vel, 0)
        regs = {POS_LOOP_GAIN: old_pos, VEL_LOOP_GAIN: old_vel, VEL_LOOP_INTEGRAL: 0}
        kp_max = max(_gains(old_pos, old_vel)[0], _gains(new_pos, new_vel)[0])
        kd_max = max(old_vel, new_vel)
        for address, value in write_order(old, new):
            regs[address] = value
            kp, kd = _gains(regs[POS_LOOP_GAIN], regs[VEL_LOOP_GAIN])
            assert kp <= kp_max and kd <= kd_max, (old, new, regs)
        assert (regs[POS_LOOP_GAIN], regs[VEL_LOOP_GAIN]) == (new_pos, new_vel)
