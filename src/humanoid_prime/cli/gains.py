"""``prime gains``: the eRob loop-gain registers for a (kp, kd) or a mode, per joint."""

from __future__ import annotations

import argparse

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import add_config_options, add_json_option, print_json, real
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.hardware import HardwareConfig
from humanoid_prime.config.robot import load_robot
from humanoid_prime.drivers.erob.gains import (
    check_mode_gains,
    gains_to_registers,
    pos_reg_exact,
    registers_to_gains,
    vel_reg_exact,
)
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "gains", help=summary("gains"),
        description="Convert stiffness kp (Nm/rad) and damping kd (Nm*s/rad), or a mode's gains, to the eRob "
                    "loop-gain registers of each eRob joint (its Kt and gear from the hardware file), and show "
                    "the kp and kd the drive realises with the rounded registers.")
    p.add_argument("--kp", type=real(at_least=0.0), metavar="KP", help="stiffness in Nm/rad")
    p.add_argument("--kd", type=real(at_least=0.0), metavar="KD", help="damping in Nm*s/rad")
    p.add_argument("--mode", metavar="MODE", help="take kp and kd from this mode (controllers file)")
    p.add_argument("--joint", metavar="NAME", help="one eRob joint (default: every eRob joint)")
    p.add_argument("--efficiency", type=real(above=0.0, at_most=1.0), metavar="E",
                   help="realised/nominal torque efficiency, 0 < E <= 1 (default: the hardware file's)")
    add_config_options(p, controllers=True)
    add_json_option(p)
    p.set_defaults(func=run)


def _requested_gains(args: argparse.Namespace, hardware: HardwareConfig) -> tuple[float, float, str | None]:
    if args.mode is not None:
        if args.kp is not None or args.kd is not None:
            raise PrimeError("give either --mode or --kp/--kd, not both")
        try:
            mode = Mode.parse(args.mode)
        except ValueError as exc:
            raise PrimeError(str(exc)) from None
        config = load_controllers(hardware.all_joints, args.controllers)
        check_mode_gains(config, hardware)
        kp, kd = config.mode_gains()[mode]
        return kp, kd, mode.value
    if args.kp is None or args.kd is None:
        raise PrimeError("give --kp and --kd (or --mode)")
    return args.kp, args.kd, None


def run(args: argparse.Namespace) -> int:
    robot = load_robot(args.hardware)
    hardware = robot.hardware
    kp, kd, mode = _requested_gains(args, hardware)
    efficiency = hardware.torque_efficiency if args.efficiency is None else args.efficiency
    joints = hardware.erob_joints
    if args.joint is not None:
        if args.joint not in robot.names:
            raise PrimeError(f"unknown joint {args.joint!r}; eRob joints: {', '.join(joints)}")
        if args.joint not in joints:
            raise PrimeError(f"{args.joint} is a Sito joint: its gains are sent per tick over CAN, "
                             f"not as eRob registers; eRob joints: {', '.join(joints)}")
        joints = (args.joint,)
    rows = []
    for joint in joints:
        kt, gear = hardware.erob_kt[joint], hardware.erob_gear[joint]
        try:
            regs = gains_to_registers(kp, kd, kt=kt, gear=gear, efficiency=efficiency)
        except ValueError as exc:
            raise PrimeError(f"{joint}: {exc}") from None
        realised_kp, realised_kd = registers_to_gains(regs, kt=kt, gear=gear, transmission_efficiency=efficiency)
        rows.append({
            "joint": joint, "ring_position": hardware.erob_slaves[joint], "mode": mode, "kp": kp, "kd": kd,
            "kt_nm_per_ma": kt, "gear": gear, "efficiency": efficiency,
            "vel_reg": regs.vel_reg, "pos_reg": regs.pos_reg, "integral": regs.integral,
            "vel_reg_exact": vel_reg_exact(kd, kt=kt, gear=gear, efficiency=efficiency),
            "pos_reg_exact": pos_reg_exact(kp, kd),
            "realised_kp": realised_kp, "realised_kd": realised_kd,
        })
    if args.json:
        print_json(rows[0] if args.joint is not None else rows)
        return 0
    what = f"{mode} " if mode else ""
    print(f"{what}kp {kp:g} Nm/rad, kd {kd:g} Nm*s/rad, efficiency {efficiency:g}")
    for r in rows:
        print(f"  {r['joint']:<22} ring {r['ring_position']}  vel_reg {r['vel_reg']:>5} ({r['vel_reg_exact']:.2f})  "
              f"pos_reg {r['pos_reg']:>5} ({r['pos_reg_exact']:.2f})  integral {r['integral']}  "
              f"-> kp {r['realised_kp']:.3f}, kd {r['realised_kd']:.4f}")
    return 0
