"""The eRob calibration fold: one per-slave config per eRob joint, calibration in the PDO factors/offsets.

The drive's NVM is never touched: ``direction`` and ``homing_offset`` become the factor/offset of the
position, velocity and effort channels (DESIGN §2), in the generic CiA402 schema that both the Python
EtherCAT component and the C++ ``ethercat_driver_ros2`` stack read. With c = counts per rad:
state position ``direction/c * raw - direction*offset``; command position ``direction*c * q + offset*c``;
velocity ``direction/c`` and ``direction*c``; effort per-mille of the rated torque, ``direction*rated/1000``
and its inverse.

For the C++ stack (ICube ``ethercat_driver_ros2``) a fold with the controllers file also carries an ``sdo:``
start-up list: the following-error window, the standby gains and the bus-gain gate, which that stack writes
once in PRE-OP. ``auto_fault_reset`` is false: a drive fault latches until the operator resets it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Required, TypedDict

from humanoid_prime.config.calibration import Calibration, JointCalibration
from humanoid_prime.config.controllers import ControllersConfig
from humanoid_prime.config.hardware import HardwareConfig
from humanoid_prime.config.robot import JointSpec, Robot
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD, MODE_CSP, PRODUCT_CODE, RATED_TORQUE_NM, VENDOR_ID
from humanoid_prime.drivers.erob.gains import check_mode_gains, following_window_counts, gains_to_registers, write_order
from humanoid_prime.drivers.erob.objects import (
    BUS_GAIN_GATE,
    FOLLOWING_ERROR_WINDOW,
    POS_LOOP_GAIN,
    RXPDO,
    RXPDO_MAP,
    TXPDO,
    TXPDO_MAP,
    VEL_LOOP_GAIN,
    PdoEntry,
)
from humanoid_prime.drivers.ethercat.slave_config import (
    CONTROL_WORD,
    ERROR_CODE,
    MODE_OF_OPERATION,
    STATUS_WORD,
    TYPE_OF_FORMAT,
)
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import atomic_write_text
from humanoid_prime.modes import Mode

ASSIGN_ACTIVATE_DC_SYNC0 = 0x0300  # DC unit: cyclic operation with SYNC0; Prime keeps DC on (DESIGN §3)
# A fault latches: with true, ICube's CiA402 plugin would clear following-error faults every cycle and
# re-enable with no operator action.
AUTO_FAULT_RESET = False
# ICube's start-up SDO types, by the size of each object (ZeroErr EDS V1.5 for the gains and 0x6065; the
# gate is absent from the EDS and UDINT in ZeroErr's parameter table).
SDO_TYPES = {FOLLOWING_ERROR_WINDOW: "int32", BUS_GAIN_GATE[0]: "uint32", POS_LOOP_GAIN[0]: "uint16",
             VEL_LOOP_GAIN[0]: "uint16"}
_HEX_KEYS = {"vendor_id": 8, "product_id": 8, "assign_activate": 4, "index": 4}

Scalar = int | float | str | bool | None
ChannelDoc = dict[str, Scalar]  # one channel: index, sub_index, type, its interface, factor, offset, default


class PdoDoc(TypedDict):
    index: int
    channels: list[ChannelDoc]


class StartupSdoDoc(TypedDict):
    index: int
    sub_index: int
    type: str
    value: int


class SlaveConfigDoc(TypedDict, total=False):
    """A per-slave config document (``slave_config.py`` reads it back)."""

    vendor_id: Required[int]
    product_id: Required[int]
    assign_activate: Required[int]
    auto_fault_reset: Required[bool]
    rpdo: Required[list[PdoDoc]]
    tpdo: Required[list[PdoDoc]]
    sdo: list[StartupSdoDoc]


def _channels(entries: tuple[PdoEntry, ...], scaled: dict[str, ChannelDoc]) -> list[ChannelDoc]:
    """The channels of a PDO, without its pad byte: IgH maps exactly what the file lists (the eRob takes any
    mapping of 0x1600/0x1A00 up to 76 bytes), and ICube's CiA402 plugin indexes its channels by domain
    position, which a gap channel would shift."""
    channels: list[ChannelDoc] = []
    for entry in entries:
        if entry.fmt == "x":
            continue
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


def startup_sdos(spec: JointSpec, hardware: HardwareConfig,
                 mode_gains: Mapping[Mode, tuple[float, float]]) -> list[StartupSdoDoc]:
    """The SDOs the C++ stack writes once in PRE-OP for eRob joint ``spec``, in order: the following-error
    window this controllers file needs (as Prime's own impedance manager sets it), the standby gains, then
    the gate that makes the drive use them. Values are plain integers, within ICube's signed 32-bit ``value``."""
    kp, kd = mode_gains[Mode.STANDBY]
    regs = gains_to_registers(kp, kd, kt=hardware.erob_kt[spec.name], gear=hardware.erob_gear[spec.name],
                              efficiency=hardware.erob_torque_efficiency[spec.name])
    writes: list[tuple[tuple[int, int], int]] = []
    window = following_window_counts(spec.effort_limit, mode_gains)
    if window is not None:
        writes.append(((FOLLOWING_ERROR_WINDOW, 0), window))
    writes += write_order(None, regs)
    writes.append((BUS_GAIN_GATE, 1))
    return [{"index": index, "sub_index": sub, "type": SDO_TYPES[index], "value": int(value)}
            for (index, sub), value in writes]


def fold_slave_config(spec: JointSpec, cal: JointCalibration,
                      sdo: list[StartupSdoDoc] | None = None) -> SlaveConfigDoc:
    """The per-slave config document of eRob joint ``spec`` with ``cal`` folded into its channels (and the
    start-up ``sdo`` list, when given)."""
    if spec.family != "erob":
        raise ValueError(f"{spec.name} is a Sito joint; only eRob joints have a slave config")
    d = float(cal.direction)
    c = COUNTS_PER_RAD
    state_offset = -d * cal.homing_offset + 0.0  # + 0.0 writes a zero offset as 0.0, not -0.0
    per_mille = 1000.0 / RATED_TORQUE_NM
    commands: dict[str, ChannelDoc] = {
        "controlword": {"command_interface": CONTROL_WORD, "default": 0},
        "target_position": {"command_interface": "position", "default": math.nan,
                            "factor": d * c, "offset": cal.homing_offset * c},
        "velocity_offset": {"command_interface": "velocity", "default": 0, "factor": d * c, "offset": 0.0},
        "torque_offset": {"command_interface": "effort", "default": 0, "factor": d * per_mille, "offset": 0.0},
        "mode_of_operation": {"command_interface": MODE_OF_OPERATION, "default": MODE_CSP},
    }
    states: dict[str, ChannelDoc] = {
        "statusword": {"state_interface": STATUS_WORD},
        "position_actual": {"state_interface": "position", "factor": d / c, "offset": state_offset},
        "velocity_actual": {"state_interface": "velocity", "factor": d / c, "offset": 0.0},
        "torque_actual": {"state_interface": "effort", "factor": d / per_mille, "offset": 0.0},
        "error_code": {"state_interface": ERROR_CODE},
        "mode_display": {"state_interface": MODE_OF_OPERATION},
    }
    doc: SlaveConfigDoc = {
        "vendor_id": VENDOR_ID,
        "product_id": PRODUCT_CODE,
        "assign_activate": ASSIGN_ACTIVATE_DC_SYNC0,
        "auto_fault_reset": AUTO_FAULT_RESET,
        "rpdo": [{"index": RXPDO_MAP, "channels": _channels(RXPDO, commands)}],
        "tpdo": [{"index": TXPDO_MAP, "channels": _channels(TXPDO, states)}],
    }
    if sdo:
        doc["sdo"] = sdo
    return doc


def _scalar(key: str, value: object, hex_keys: dict[str, int]) -> str:
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


def _flow(mapping: Mapping[str, object], hex_keys: dict[str, int]) -> str:
    return "{" + ", ".join(f"{k}: {_scalar(k, v, hex_keys)}" for k, v in mapping.items()) + "}"


def render_slave_config(doc: SlaveConfigDoc, header: str = "") -> str:
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
    if doc.get("sdo"):
        lines.append("sdo:")
        lines.extend(f"  - {_flow(entry, _HEX_KEYS)}" for entry in doc["sdo"])
    return "\n".join(lines) + "\n"


def _header(spec: JointSpec, cal: JointCalibration, source: Path | None) -> str:
    origin = f" from {source}" if source is not None else ""
    return (f"# eRob slave config of {spec.name} (ring position {spec.ring_position}), generated by "
            f"`prime calibration fold`{origin}.\n"
            f"# Folded calibration: direction {cal.direction}, homing_offset {cal.homing_offset!r} rad. "
            "Regenerate, do not edit.\n"
            "# Channels convert with value = factor * x + offset in both directions. ethercat_driver_ros2 truncates\n"
            "# a command toward zero where Prime rounds it, so the two can differ by one count.\n"
            "# auto_fault_reset is false: a drive fault latches until the operator resets it.\n"
            "# The effort factors assume the nominal rated torque (0x6076) of "
            f"{RATED_TORQUE_NM:g} N*m; Prime reads each drive's own.\n"
            "# sdo: written once in PRE-OP (following-error window, standby gains, then the bus-gain gate);\n"
            "# a drive that holds the gains in another size refuses them, and that stack only logs it.\n")


def write_folded_configs(robot: Robot, calibration: Calibration, out_dir: str | Path,
                         controllers: ControllersConfig | None = None) -> list[Path]:
    """Write ``<joint>.yaml`` for every eRob joint of ``robot`` into ``out_dir``, each atomically; with
    ``controllers``, each also gets its start-up ``sdo:`` list (standby gains)."""
    check_foldable(robot, calibration)
    mode_gains = None
    if controllers is not None:
        check_mode_gains(controllers, robot.hardware)
        mode_gains = controllers.mode_gains()
    out_dir = Path(out_dir)
    written = []
    for spec in robot.joints:
        if spec.family != "erob":
            continue
        cal = calibration.joints[spec.name]
        path = out_dir / f"{spec.name}.yaml"
        sdo = startup_sdos(spec, robot.hardware, mode_gains) if mode_gains is not None else None
        atomic_write_text(path, render_slave_config(fold_slave_config(spec, cal, sdo),
                                                    _header(spec, cal, calibration.path)))
        written.append(path)
    return written
