"""Per-slave EtherCAT configs in the generic CiA402 schema of ``ethercat_driver_ros2``: model and loader.

A config lists the slave's identity, its DC activation word, its RxPDO/TxPDO channels and, optionally,
the SDOs written once at start-up (``sdo:``, each ``{index, sub_index, type, value}``; ``value`` is read
as a signed 32-bit integer by ``ethercat_driver_ros2``, so it must fit one, whatever the type). A channel
with a ``command_interface`` (RxPDO) or ``state_interface`` (TxPDO) converts between the interface value
and the raw PDO value with ``value = factor * x + offset`` in both directions: state = factor * raw +
offset, raw = factor * command + offset. The eRob calibration is folded into those factors and offsets.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from humanoid_prime.errors import ConfigError
from humanoid_prime.files import load_yaml

# PDO data types by their schema name: (struct format, smallest, largest value).
PDO_TYPES: dict[str, tuple[str, int, int]] = {
    "int8": ("b", -(1 << 7), (1 << 7) - 1),
    "uint8": ("B", 0, (1 << 8) - 1),
    "int16": ("h", -(1 << 15), (1 << 15) - 1),
    "uint16": ("H", 0, (1 << 16) - 1),
    "int32": ("i", -(1 << 31), (1 << 31) - 1),
    "uint32": ("I", 0, (1 << 32) - 1),
    "int64": ("q", -(1 << 63), (1 << 63) - 1),
    "uint64": ("Q", 0, (1 << 64) - 1),
}
_Choice = TypeVar("_Choice", str, str | None)
TYPE_OF_FORMAT = {fmt: name for name, (fmt, _, _) in PDO_TYPES.items()}

# Interface names of the CiA402 housekeeping channels (the MIT ones are position, velocity, effort).
CONTROL_WORD = "control_word"
STATUS_WORD = "status_word"
MODE_OF_OPERATION = "mode_of_operation"
ERROR_CODE = "error_code"


@dataclass(frozen=True)
class Channel:
    index: int
    sub_index: int
    type: str
    interface: str | None
    factor: float = 1.0
    offset: float = 0.0
    default: float = math.nan

    def state_value(self, raw: float) -> float:
        """Interface value of a raw TxPDO value."""
        return self.factor * raw + self.offset

    def command_raw(self, x: float) -> int:
        """Raw RxPDO value for interface value ``x``, rounded to the nearest integer and clamped to the type."""
        if not math.isfinite(x):
            raise ValueError(f"channel 0x{self.index:04X}: command {x!r} is not finite")
        _, lo, hi = PDO_TYPES[self.type]
        value = self.factor * x + self.offset
        return lo if value <= lo else hi if value >= hi else math.floor(value + 0.5)

    def unfold_state(self, value: float) -> float:
        """The raw TxPDO value that reads as interface ``value`` (inverse of ``state_value``)."""
        return (value - self.offset) / self.factor

    def unfold_command(self, raw: float) -> float:
        """The interface value that ``raw`` was commanded from (inverse of ``command_raw`` before rounding)."""
        return (raw - self.offset) / self.factor


@dataclass(frozen=True)
class Pdo:
    index: int
    channels: tuple[Channel, ...]


@dataclass(frozen=True)
class SyncManager:
    index: int
    type: str  # "output" or "input"
    pdo: str | None  # "rpdo", "tpdo" or None
    watchdog: str | None  # "enable", "disable" or None (slave default)


@dataclass(frozen=True)
class StartupSdo:
    index: int
    sub_index: int
    type: str
    value: int

    @property
    def data(self) -> bytes:
        """The bytes of the download (little-endian, the type's size)."""
        return struct.pack("<" + PDO_TYPES[self.type][0], self.value)


@dataclass(frozen=True)
class SlaveConfig:
    source: str  # the file it was read from, or what generated it
    vendor_id: int
    product_id: int
    assign_activate: int
    auto_fault_reset: bool
    rpdo: tuple[Pdo, ...]
    tpdo: tuple[Pdo, ...]
    sm: tuple[SyncManager, ...]
    sdo: tuple[StartupSdo, ...] = ()

    @property
    def rpdo_channels(self) -> tuple[Channel, ...]:
        return tuple(c for pdo in self.rpdo for c in pdo.channels)

    @property
    def tpdo_channels(self) -> tuple[Channel, ...]:
        return tuple(c for pdo in self.tpdo for c in pdo.channels)

    def command(self, interface: str) -> Channel:
        """The RxPDO channel of a command interface; a config without it raises ConfigError."""
        return self._find(self.rpdo_channels, interface, "rpdo", "command_interface")

    def state(self, interface: str) -> Channel:
        """The TxPDO channel of a state interface; a config without it raises ConfigError."""
        return self._find(self.tpdo_channels, interface, "tpdo", "state_interface")

    def _find(self, channels: tuple[Channel, ...], interface: str, section: str, key: str) -> Channel:
        for channel in channels:
            if channel.interface == interface:
                return channel
        raise ConfigError(self.source, section, f"no channel with {key}: {interface}",
                          "regenerate it with `prime calibration fold`")


def _int(value: object, path: str | Path, key: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        span = f"{lo}..{hi}" if lo < 0 else f"0x{lo:X}..0x{hi:X}"
        raise ConfigError(path, key, f"expected an integer in {span}, got {value!r}")
    return value


def _number(value: object, path: str | Path, key: str, *, allow_nan: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(path, key, f"expected a number, got {value!r}")
    if not (math.isfinite(value) or (allow_nan and math.isnan(value))):
        raise ConfigError(path, key, f"expected a finite number{' or .nan' if allow_nan else ''}, got {value!r}")
    return float(value)


def _choice(value: object, path: str | Path, key: str, choices: tuple[_Choice, ...]) -> _Choice:
    if value not in choices:
        names = ", ".join("~" if c is None else c for c in choices)
        raise ConfigError(path, key, f"expected one of {names}, got {value!r}")
    return choices[choices.index(value)]  # the choice ``value`` equals, typed as one


def _channel(raw: object, path: str | Path, key: str, interface_key: str, other_key: str) -> Channel:
    if not isinstance(raw, dict):
        raise ConfigError(path, key, "expected a mapping {index, sub_index, type, ...}")
    if other_key in raw:
        raise ConfigError(path, f"{key}.{other_key}", f"not allowed here; use {interface_key}")
    type_name = raw.get("type")
    if type_name not in PDO_TYPES:
        raise ConfigError(path, f"{key}.type", f"unknown type {type_name!r}", f"use one of {', '.join(PDO_TYPES)}")
    interface = raw.get(interface_key)
    if interface is not None and (not isinstance(interface, str) or not interface):
        raise ConfigError(path, f"{key}.{interface_key}", f"expected a name or ~, got {interface!r}")
    factor = _number(raw.get("factor", 1.0), path, f"{key}.factor")
    if factor == 0:
        raise ConfigError(path, f"{key}.factor", "must not be 0", "a zero factor makes the interface constant")
    return Channel(
        index=_int(raw.get("index"), path, f"{key}.index", 0, 0xFFFF),
        sub_index=_int(raw.get("sub_index", 0), path, f"{key}.sub_index", 0, 0xFF),
        type=type_name,
        interface=interface,
        factor=factor,
        offset=_number(raw.get("offset", 0.0), path, f"{key}.offset"),
        default=_number(raw.get("default", math.nan), path, f"{key}.default", allow_nan=True),
    )


def _mappings(data: dict[str, object], section: str, path: str | Path,
              fields: str) -> Iterator[tuple[str, dict[str, object]]]:
    """The entries of the list ``section`` (absent: none), each with its key (``section[i]``); anything but a
    list of mappings with ``fields`` is refused naming the key."""
    raw = data.get(section, [])
    if not isinstance(raw, list):
        raise ConfigError(path, section, f"expected a list of {{{fields}}}")
    for i, entry in enumerate(raw):
        key = f"{section}[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(path, key, f"expected a mapping {{{fields}}}")
        yield key, entry


def _pdos(data: dict[str, object], path: str | Path, section: str) -> tuple[Pdo, ...]:
    interface_key, other_key = (("command_interface", "state_interface") if section == "rpdo"
                                else ("state_interface", "command_interface"))
    pdos = []
    seen: dict[str, str] = {}
    for key, entry in _mappings(data, section, path, "index, channels"):
        channels_raw = entry.get("channels")
        if not isinstance(channels_raw, list) or not channels_raw:
            raise ConfigError(path, f"{key}.channels", "missing or empty", "list the mapped objects")
        channels = []
        for j, raw_channel in enumerate(channels_raw):
            ckey = f"{key}.channels[{j}]"
            channel = _channel(raw_channel, path, ckey, interface_key, other_key)
            if channel.interface is not None:
                if channel.interface in seen:
                    raise ConfigError(path, f"{ckey}.{interface_key}",
                                      f"{channel.interface!r} is already mapped at {seen[channel.interface]}")
                seen[channel.interface] = ckey
            channels.append(channel)
        pdos.append(Pdo(_int(entry.get("index"), path, f"{key}.index", 0, 0xFFFF), tuple(channels)))
    return tuple(pdos)


def _sync_managers(data: dict[str, object], path: str | Path) -> tuple[SyncManager, ...]:
    result = []
    for key, entry in _mappings(data, "sm", path, "index, type, pdo, watchdog"):
        result.append(SyncManager(
            index=_int(entry.get("index"), path, f"{key}.index", 0, 0xFF),
            type=_choice(entry.get("type"), path, f"{key}.type", ("output", "input")),
            pdo=_choice(entry.get("pdo"), path, f"{key}.pdo", ("rpdo", "tpdo", None)),
            watchdog=_choice(entry.get("watchdog"), path, f"{key}.watchdog", ("enable", "disable", None)),
        ))
    return tuple(result)


def _startup_sdos(data: dict[str, object], path: str | Path) -> tuple[StartupSdo, ...]:
    result = []
    for key, entry in _mappings(data, "sdo", path, "index, sub_index, type, value"):
        missing = [k for k in ("index", "sub_index", "type", "value") if k not in entry]
        if missing:
            raise ConfigError(path, f"{key}.{missing[0]}", "missing", "every start-up SDO needs index, sub_index, "
                                                                      "type and value")
        type_name = entry["type"]
        if type_name not in PDO_TYPES:
            raise ConfigError(path, f"{key}.type", f"unknown type {type_name!r}", f"use one of {', '.join(PDO_TYPES)}")
        _, lo, hi = PDO_TYPES[type_name]
        value = _int(entry["value"], path, f"{key}.value", max(lo, -(1 << 31)), min(hi, (1 << 31) - 1))
        result.append(StartupSdo(_int(entry["index"], path, f"{key}.index", 0, 0xFFFF),
                                 _int(entry["sub_index"], path, f"{key}.sub_index", 0, 0xFF), type_name, value))
    return tuple(result)


def load_slave_config(path: str | Path) -> SlaveConfig:
    """Load and validate one per-slave config file; every error names the file and the key."""
    path = Path(path)
    return parse_slave_config(load_yaml(path), path)


def parse_slave_config(data: object, source: str | Path) -> SlaveConfig:
    """Validate one per-slave config document (as YAML loads it); errors name ``source`` (a file, or what
    generated the document) and the key."""
    path = source
    if not isinstance(data, dict):
        raise ConfigError(path, "", "expected a mapping with vendor_id, product_id, rpdo, tpdo")
    auto_fault_reset = data.get("auto_fault_reset", False)
    if not isinstance(auto_fault_reset, bool):
        raise ConfigError(path, "auto_fault_reset", f"expected true or false, got {auto_fault_reset!r}")
    return SlaveConfig(
        source=str(source),
        vendor_id=_int(data.get("vendor_id"), path, "vendor_id", 0, 0xFFFFFFFF),
        product_id=_int(data.get("product_id"), path, "product_id", 0, 0xFFFFFFFF),
        assign_activate=_int(data.get("assign_activate", 0), path, "assign_activate", 0, 0xFFFF),
        auto_fault_reset=auto_fault_reset,
        rpdo=_pdos(data, path, "rpdo"),
        tpdo=_pdos(data, path, "tpdo"),
        sm=_sync_managers(data, path),
        sdo=_startup_sdos(data, path),
    )
