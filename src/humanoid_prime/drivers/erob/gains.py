"""eRob impedance: SI (kp, kd) <-> the drive's loop-gain registers (DESIGN §2).

The drive runs a cascaded position -> velocity (PI) loop; with the integral held at 0 it linearises to
``kp = Kpos * Kvel`` and ``kd = Kvel``. Hence ``vel_reg`` carries the damping and ``pos_reg`` only the
ratio ``kp / kd``. kd = 0 sends both to 0 (true limp); stiffness without damping cannot be realised.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from humanoid_prime.config.controllers import ControllersConfig
from humanoid_prime.config.hardware import DEFAULT_GEAR, DEFAULT_KT_NM_PER_MA, HardwareConfig
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD
from humanoid_prime.drivers.erob.objects import POS_LOOP_GAIN, VEL_LOOP_GAIN, VEL_LOOP_INTEGRAL
from humanoid_prime.errors import ConfigError
from humanoid_prime.modes import Mode

KD_PER_VEL_REG_NM_S_PER_RAD = 0.1063  # damping of one vel_reg step, eRob70 Kt at 50:1; measured, see DESIGN §2
POS_REG_PER_RATIO_S = 51.47  # pos_reg per unit kp/kd (1/s); model-independent, see DESIGN §2
REFERENCE_KT_GEAR_NM_PER_MA = DEFAULT_KT_NM_PER_MA * DEFAULT_GEAR  # the Kt*gear the 0.1063 was measured at
FOLLOWING_WINDOW_MARGIN = 2.0  # the following-error window over the sag at the effort limit (see below)
REGISTER_MAX = 0xFFFF  # the EDS declares the gain registers u16 (one ESI says u32; the narrower one binds)


@dataclass(frozen=True)
class ErobRegisters:
    """The three loop-gain registers as integers, as the drive holds them."""

    pos_reg: int
    vel_reg: int
    integral: int


def vel_reg_exact(kd: float, *, kt: float = DEFAULT_KT_NM_PER_MA, gear: float = DEFAULT_GEAR,
                  efficiency: float = 1.0) -> float:
    """Velocity-loop register for damping ``kd`` (Nm*s/rad), before rounding.

    Scales with the reference Kt*gear over this joint's, and is divided by ``efficiency`` (realised/nominal)
    so the drive realises the asked kd (and, through it, kp).
    """
    return kd / KD_PER_VEL_REG_NM_S_PER_RAD * (REFERENCE_KT_GEAR_NM_PER_MA / (kt * gear)) / efficiency


def pos_reg_exact(kp: float, kd: float) -> float:
    """Position-loop register for (kp, kd), before rounding: the ratio only; 0 when kd is 0."""
    if kd == 0:
        return 0.0
    return kp / kd * POS_REG_PER_RATIO_S


def _check_model(kt: float, gear: float, efficiency: float) -> None:
    for name, value in (("kt", kt), ("gear", gear)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    if not (math.isfinite(efficiency) and 0 < efficiency <= 1):
        raise ValueError(f"efficiency must be realised/nominal in (0, 1], got {efficiency!r}")


def _register(name: str, exact: float, why: str) -> int:
    if not exact + 0.5 < REGISTER_MAX + 1:  # also an infinite ratio: compared before any rounding
        raise ValueError(f"{name} {exact:.1f} does not fit the u16 register (max {REGISTER_MAX}); {why}")
    return math.floor(exact + 0.5)


def gains_to_registers(kp: float, kd: float, *, kt: float = DEFAULT_KT_NM_PER_MA, gear: float = DEFAULT_GEAR,
                       efficiency: float = 1.0) -> ErobRegisters:
    """Registers (rounded to the nearest integer) that realise stiffness ``kp`` (Nm/rad) and damping ``kd``.

    Raises ValueError for a negative or non-finite gain, for kp > 0 with kd = 0 (stiffness without damping
    cannot be realised on this drive), for a kd too small to reach one register step, or for a register
    value beyond u16.
    """
    _check_model(kt, gear, efficiency)
    for name, value in (("kp", kp), ("kd", kd)):
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    if kd == 0:
        if kp > 0:
            raise ValueError(f"kp {kp:g} with kd 0 cannot be realised: eRob stiffness is pos_reg * vel_reg, "
                             "so stiffness needs damping; give kd > 0, or kp 0 for a limp joint")
        return ErobRegisters(pos_reg=0, vel_reg=0, integral=0)
    vel_reg = _register("vel_reg", vel_reg_exact(kd, kt=kt, gear=gear, efficiency=efficiency),
                        f"kd {kd:g} Nm*s/rad is too high")
    if vel_reg == 0:
        step = KD_PER_VEL_REG_NM_S_PER_RAD * (kt * gear) / REFERENCE_KT_GEAR_NM_PER_MA * efficiency
        raise ValueError(f"kd {kd:g} Nm*s/rad rounds to vel_reg 0 (one step is {step:.4f} Nm*s/rad); "
                         f"use kd >= {step / 2:.4f}, or kd 0 for a limp joint")
    pos_reg = _register("pos_reg", pos_reg_exact(kp, kd), f"kp/kd = {kp / kd:g} 1/s is too high")
    return ErobRegisters(pos_reg=pos_reg, vel_reg=vel_reg, integral=0)


def registers_to_gains(regs: ErobRegisters, *, kt: float = DEFAULT_KT_NM_PER_MA, gear: float = DEFAULT_GEAR,
                       transmission_efficiency: float = 1.0) -> tuple[float, float]:
    """The (kp, kd) the drive realises with ``regs``.

    ``transmission_efficiency`` is the realised/nominal ratio of the physical drive (about 0.7 on Prime);
    1.0 gives the nominal values.
    """
    _check_model(kt, gear, transmission_efficiency)
    kd = (regs.vel_reg * KD_PER_VEL_REG_NM_S_PER_RAD * (kt * gear) / REFERENCE_KT_GEAR_NM_PER_MA
          * transmission_efficiency)
    kp = regs.pos_reg / POS_REG_PER_RATIO_S * kd
    return kp, kd


def write_order(old: ErobRegisters | None, new: ErobRegisters) -> list[tuple[tuple[int, int], int]]:
    """The SDO writes, as ((index, sub_index), value), that take the drive from ``old`` to ``new``.

    Only registers whose value changes are written (all three when ``old`` is unknown). The integral goes
    first. When damping falls, vel_reg goes before pos_reg, otherwise pos_reg first: either way the state
    between the two writes is no stiffer (kp = pos*vel) and no more damped (kd = vel) than the stiffer and
    more damped of ``old`` and ``new``.
    """
    writes: list[tuple[tuple[int, int], int]] = []
    if old is None or old.integral != new.integral:
        writes.append((VEL_LOOP_INTEGRAL, new.integral))
    pos = (POS_LOOP_GAIN, new.pos_reg)
    vel = (VEL_LOOP_GAIN, new.vel_reg)
    if old is None:
        return [*writes, pos, vel]
    gains = [vel, pos] if new.vel_reg < old.vel_reg else [pos, vel]
    changed = {POS_LOOP_GAIN: new.pos_reg != old.pos_reg, VEL_LOOP_GAIN: new.vel_reg != old.vel_reg}
    return writes + [write for write in gains if changed[write[0]]]


def check_mode_gains(config: ControllersConfig, hardware: HardwareConfig) -> None:
    """Every mode's eRob (kp, kd) must be realisable on every eRob joint with its Kt, gear and the torque
    efficiency; ConfigError names the controllers file and the key otherwise."""
    keys = config.mode_gain_keys()
    for mode, (kp, kd) in config.mode_gains().items():
        kp_key, kd_key = keys[mode]
        for joint in hardware.erob_joints:
            try:
                gains_to_registers(kp, kd, kt=hardware.erob_kt[joint], gear=hardware.erob_gear[joint],
                                   efficiency=hardware.erob_torque_efficiency[joint])
            except ValueError as exc:
                key = kp_key if str(exc).startswith("pos_reg") else kd_key  # pos_reg carries kp/kd, vel_reg kd
                raise ConfigError(config.path, key or "", f"{mode.value} on {joint}: {exc}") from None


def check_erob_limits(hardware: HardwareConfig) -> None:
    """The hardware file's eRob command limits must be realisable: the stiffness and damping in the loop-gain
    registers of every eRob joint, the velocity in the INT32 velocity offset (0x60B1, counts/s)."""
    limits = hardware.command_limits["erob"]
    for joint in hardware.erob_joints:
        try:
            gains_to_registers(limits.stiffness, limits.damping, kt=hardware.erob_kt[joint],
                               gear=hardware.erob_gear[joint], efficiency=hardware.erob_torque_efficiency[joint])
        except ValueError as exc:
            name = "stiffness" if str(exc).startswith("pos_reg") else "damping"
            raise ConfigError(hardware.path, f"command_limits.erob.{name}", f"on {joint}: {exc}",
                              "a limit no drive can be set to limits nothing") from None
    reach = (2**31 - 1) / COUNTS_PER_RAD
    if limits.velocity > reach:
        raise ConfigError(hardware.path, "command_limits.erob.velocity", f"{limits.velocity:g} rad/s is beyond what "
                          f"the eRob velocity offset carries ({reach:.6g} rad/s)", "use a velocity the joint can reach")


def following_window_counts(effort_limit: float, mode_gains: Mapping[Mode, tuple[float, float]]) -> int | None:
    """The following-error window (counts) a joint needs: the margin times its sag when holding its effort
    limit at the smallest non-zero kp of the modes; None when no mode is stiff (every target follows)."""
    stiff = [kp for kp, _ in mode_gains.values() if kp > 0]
    if not stiff:
        return None
    return round(FOLLOWING_WINDOW_MARGIN * effort_limit / min(stiff) * COUNTS_PER_RAD)
