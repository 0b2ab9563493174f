"""The eRob calibration fold: one per-slave config per eRob joint, calibration in the PDO factors/offsets.

The drive's NVM is never touched: ``direction`` and ``homing_offset`` become the factor/offset of the
position, velocity and effort channels (DESIGN §2), in the generic CiA402 schema that both the Python
EtherCAT component and the C++ ``ethercat_driver_ros2`` stack read. With c = counts per rad:
state position ``direction/c * raw - direction*offset``; command position ``direction*c * q + offset*c``;
velocity ``direction/c`` and ``direction*c``; effort per-mille of the rated torque, ``direction*rated/1000``
and its inverse.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from humanoid_prime.config.calibration import Calibration, JointCalibration
from humanoid_prime.config.robot import JointSpec, Robot
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD, MODE_CSP, PRODUCT_CODE, RATED_TORQUE_NM, VENDOR_ID
from humanoid_prime.drivers.erob.objects import RXPDO, RXPDO_MAP, TXPDO, TXPDO_MAP, PdoEntry
from humanoid_prime.drivers.ethercat.slave_config import (
    CONTROL_WORD,
    ERROR_CODE,
    MODE_OF_OPERATION,
    STATUS_WORD,
    TYPE_OF_FORMAT,
)
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import atomic_write_text

ASSIGN_ACTIVATE_DC_SYNC0 = 0x0300  # DC unit: cyclic operation with SYNC0; Prime keeps DC on (DESIGN §3)
AUTO_FAULT_RESET = True  # the drive recovers from transient bring-up faults without a reset command
SYNC_MANAGERS = (  # mailbox out/in, then process data with the output watchdog on
    {"index": 0, "type": "output", "pdo": None, "watchdog": "disable"},
    {"index": 1, "type": "input", "pdo": None, "watchdog": "disable"},
    {"index": 2, "type": "output", "pdo": "rpdo", "watchdog": "enable"},
    {"index": 3, "type": "input", "pdo": "tpdo", "watchdog": "disable"},
)
_HEX_KEYS = {"vendor_id": 8, "product_id": 8, "assign_activate": 4, "index": 4}


def _channels(entries: tuple[PdoEntry, ...], scaled: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    channels = []
    for entry in entries:
        channels.append({"index": entry.index, "sub_index": entry.sub_index, "type": TYPE_OF_FORMAT[entry.fmt],
                         **scaled[entry.name]})
    return channels


def check_foldable(robot: Robot, calibration: Calibration) -> None:
    """Every eRob joint's raw position over its whole range must fit the drive's 32-bit position (0x6064,
    0x607A); ConfigError names the calibration file and the joint's key otherwise."""
    reach = 2**31 / COUNTS_PER_RAD
    for spec in robot.joints:
        if spec.family != "erob":
            continue
        offset = calibration.joints[spec.name].homing_offset
        farthest = abs(offset) + max(abs(spec.lower), abs(spec.upper))
        if farthest >= reach:
            raise ConfigError(calibration.path or "calibration", f"joints.{spec.name}.homing_offset",
                              f"{offset:g} rad puts the joint's range beyond the eRob's 32-bit position "
                              f"(+-{reach:.0f} rad)", "re-run prime calibrate")


def fold_slave_config(spec: JointSpec, cal: JointCalibration) -> dict[str, Any]:
    """The per-slave config document of eRob joint ``spec`` with ``cal`` folded into its channels."""
    if spec.family != "erob":
        raise ValueError(f"{spec.name} is a Sito joint; only eRob joints have a slave config")
    d = float(cal.direction)
    c = COUNTS_PER_RAD
    state_offset = -d * cal.homing_offset + 0.0  # + 0.0 writes a zero offset as 0.0, not -0.0
    per_mille = 1000.0 / RATED_TORQUE_NM
    commands = {
        "controlword": {"command_interface": CONTROL_WORD, "default": 0},
        "target_position": {"command_interface": "position", "default": math.nan,
                            "factor": d * c, "offset": cal.homing_offset * c},
        "velocity_offset": {"command_interface": "velocity", "default": 0, "factor": d * c, "offset": 0.0},
        "torque_offset": {"command_interface": "effort", "default": 0, "factor": d * per_mille, "offset": 0.0},
        "mode_of_operation": {"command_interface": MODE_OF_OPERATION, "default": MODE_CSP},
    }
    states = {
        "statusword": {"state_interface": STATUS_WORD},
        "position_actual": {"state_interface": "position", "factor": d / c, "offset": state_offset},
        "velocity_actual": {"state_interface": "velocity", "factor": d / c, "offset": 0.0},
        "torque_actual": {"state_interface": "effort", "factor": d / per_mille, "offset": 0.0},
        "error_code": {"state_interface": ERROR_CODE},
        "mode_display": {"state_interface": MODE_OF_OPERATION},
    }
    return {
        "vendor_id": VENDOR_ID,
        "product_id": PRODUCT_CODE,
        "assign_activate": ASSIGN_ACTIVATE_DC_SYNC0,
        "auto_fault_reset": AUTO_FAULT_RESET,
        "rpdo": [{"index": RXPDO_MAP, "channels": _channels(RXPDO, commands)}],
        "tpdo": [{"index": TXPDO_MAP, "channels": _channels(TXPDO, states)}],
        "sm": [dict(sm) for sm in SYNC_MANAGERS],
    }


def _scalar(key: str, value: Any, hex_keys: dict[str, int]) -> str:
    if value is None:
        return "~"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return f"0x{value:0{hex_keys[key]}X}" if key in hex_keys else str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return ".nan"
        if math.isinf(value):
            return ".inf" if value > 0 else "-.inf"
        text = repr(value)
        mantissa, _, exponent = text.partition("e")
        if "." not in mantissa:  # YAML 1.1 readers need the dot to see a float
            mantissa += ".0"
        return f"{mantissa}e{exponent}" if exponent else mantissa
    return str(value)


def _flow(mapping: dict[str, Any], hex_keys: dict[str, int]) -> str:
    return "{" + ", ".join(f"{k}: {_scalar(k, v, hex_keys)}" for k, v in mapping.items()) + "}"


def render_slave_config(doc: dict[str, Any], header: str = "") -> str:
    """YAML text of a slave config document: hex identities and indices, one flow mapping per channel."""
    lines = [header.rstrip("\n")] if header else []
    for key in ("vendor_id", "product_id", "assign_activate", "auto_fault_reset"):
        lines.append(f"{key}: {_scalar(key, doc[key], _HEX_KEYS)}")
    for section in ("rpdo", "tpdo"):
        lines.append(f"{section}:")
        for pdo in doc[section]:
            lines.append(f"  - index: {_scalar('index', pdo['index'], _HEX_KEYS)}")
            lines.append("    channels:")
            lines.extend(f"      - {_flow(channel, _HEX_KEYS)}" for channel in pdo["channels"])
    lines.append("sm:")
    lines.extend(f"  - {_flow(sm, {})}" for sm in doc["sm"])  # sync manager numbers stay decimal
    return "\n".join(lines) + "\n"


def _header(spec: JointSpec, cal: JointCalibration, source: Path | None) -> str:
    origin = f" from {source}" if source is not None else ""
    return (f"# eRob slave config of {spec.name} (ring position {spec.ring_position}), generated by "
            f"`prime calibration fold`{origin}.\n"
            f"# Folded calibration: direction {cal.direction}, homing_offset {cal.homing_offset!r} rad. "
            "Regenerate, do not edit.\n"
            "# Channels convert with value = factor * x + offset in both directions.\n")


def write_folded_configs(robot: Robot, calibration: Calibration, out_dir: str | Path) -> list[Path]:
    """Write ``<joint>.yaml`` for every eRob joint of ``robot`` into ``out_dir``, each atomically."""
    check_foldable(robot, calibration)
    out_dir = Path(out_dir)
    written = []
    for spec in robot.joints:
        if spec.family != "erob":
            continue
        cal = calibration.joints[spec.name]
        path = out_dir / f"{spec.name}.yaml"
        atomic_write_text(path, render_slave_config(fold_slave_config(spec, cal), _header(spec, cal, calibration.path)))
        written.append(path)
    return written
