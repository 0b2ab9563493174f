"""``prime info``: the joint topology (family, bus, address, limits, calibration) in canonical order."""

from __future__ import annotations

import argparse
from typing import TypedDict

from rich.table import Table

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import add_config_options, add_json_option, console, print_json
from humanoid_prime.config.calibration import load_calibration
from humanoid_prime.config.robot import load_robot


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("info", help=summary("info"),
                              description="Show Prime's 14 joints in canonical order with the bus and address "
                                          "each lives on, the described limits and the calibration.")
    add_config_options(p, calibration=True)
    add_json_option(p)
    p.set_defaults(func=run)


class JointRow(TypedDict):
    """One joint of ``prime info``: where it is, its limits and its calibration."""

    index: int
    joint: str
    family: str
    bus: str
    address: str
    ring_position: int | None
    can_id: int | None
    lower: float
    upper: float
    effort_limit: float
    velocity_limit: float
    direction: int
    homing_offset: float


def run(args: argparse.Namespace) -> int:
    robot = load_robot(args.hardware)
    calibration = load_calibration(robot.hardware, args.calibration)
    rows: list[JointRow] = []
    for j in robot.joints:
        cal = calibration.joints[j.name]
        rows.append({
            "index": j.index, "joint": j.name, "family": j.family, "bus": j.bus, "address": j.address,
            "ring_position": j.ring_position, "can_id": j.can_id, "lower": j.lower, "upper": j.upper,
            "effort_limit": j.effort_limit, "velocity_limit": j.velocity_limit,
            "direction": cal.direction, "homing_offset": cal.homing_offset,
        })
    if args.json:
        print_json(rows)
        return 0
    calibration_file = calibration.path.name if calibration.path is not None else "no calibration file"
    table = Table(title=f"Prime joints ({robot.hardware.path.name}, {calibration_file})")
    for name in ("#", "joint", "family", "bus", "address", "lower", "upper", "effort", "direction", "offset"):
        table.add_column(name, no_wrap=True,
                         justify="right" if name in ("#", "lower", "upper", "effort", "offset") else "left")
    for r in rows:
        table.add_row(str(r["index"]), r["joint"], r["family"], r["bus"], r["address"], f"{r['lower']:+.3f}",
                      f"{r['upper']:+.3f}", f"{r['effort_limit']:g}", f"{r['direction']:+d}",
                      f"{r['homing_offset']:+.4f}")
    console().print(table)
    return 0
