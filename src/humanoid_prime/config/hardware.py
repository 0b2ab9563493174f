"""``prime_hardware.yaml``: buses and the joint -> bus map (the single source of truth for both)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from humanoid_prime.errors import ConfigError
from humanoid_prime.files import bundled, check_keys, config_path, load_yaml

HARDWARE_FILE = "prime_hardware.yaml"
CAN_ID_RANGE = range(1, 256)  # the id is one byte of the Sito arbitration id
# What an eRob joint without its own joints.erob_kt / joints.erob_gear entry has (DESIGN §2).
DEFAULT_KT_NM_PER_MA = 0.132e-3  # eRob70 V4_MC2 motor torque constant
DEFAULT_GEAR = 50.0  # every Prime eRob is 50:1
FAMILIES = ("erob", "sito")
MAX_COLLISION_MARGIN_M = 0.2  # more keeps the hands from ever meeting in front of the torso
MAX_STOPPING_TIME_S = 1.0  # an arm that needs longer to stop has no business near another
SAFETY_KEYS = ("collision_margin", "stopping_time")


@dataclass(frozen=True)
class EthercatBus:
    interface: str
    master: int
    mailbox: str = "prime"  # who works the eRob's mailboxes: Prime's CoE layer, or SOEM alone (the way back)


@dataclass(frozen=True)
class CanBus:
    interface: str
    channel: str
    bitrate: int


@dataclass(frozen=True)
class CommandLimits:
    """The most a joint of one family takes from any command: stiffness (Nm/rad), damping (Nm*s/rad) and
    |velocity| (rad/s)."""

    stiffness: float
    damping: float
    velocity: float


@dataclass(frozen=True)
class HardwareConfig:
    path: Path
    ethercat: EthercatBus
    can: CanBus
    all_joints: tuple[str, ...]
    erob_slaves: dict[str, int]
    mit_joints: dict[str, int]
    erob_kt: dict[str, float]
    erob_gear: dict[str, float]
    torque_efficiency: float
    command_limits: dict[str, CommandLimits]  # per family
    # Per eRob joint, realised/nominal stiffness: ``joints.erob_torque_efficiency``, else ``torque_efficiency``.
    erob_torque_efficiency: dict[str, float]
    # Per joint given in ``joints.contact_effort_cap`` (Nm): what `prime calibrate --auto` may push a stop with.
    contact_effort_cap: dict[str, float]
    # ``safety.collision_margin`` (m): how close the command gate lets two bodies of the robot come.
    collision_margin: float
    # ``safety.stopping_time`` (s): how far ahead along a moving joint's velocity the gate looks for where it stops.
    stopping_time: float

    @property
    def erob_joints(self) -> tuple[str, ...]:
        """eRob joints in canonical (kinematic) order."""
        return tuple(j for j in self.all_joints if j in self.erob_slaves)

    @property
    def sito_joints(self) -> tuple[str, ...]:
        """Sito joints in canonical (kinematic) order."""
        return tuple(j for j in self.all_joints if j in self.mit_joints)

    def family(self, joint: str) -> str:
        return "erob" if joint in self.erob_slaves else "sito"


def _section(data: object, path: Path, key: str) -> dict[str, object]:
    value = data.get(key.rsplit(".", 1)[-1]) if isinstance(data, dict) else None
    if not isinstance(value, dict):
        raise ConfigError(path, key, "missing or not a mapping", f"add a '{key}' mapping")
    return value


def _int(value: object, path: Path, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(path, key, f"expected an integer, got {value!r}")
    return value


def _positive_float(value: object, path: Path, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ConfigError(path, key, f"expected a positive finite number, got {value!r}")
    return float(value)


def _str(value: object, path: Path, key: str) -> str:
    if not isinstance(value, str) or not value:
        raise ConfigError(path, key, f"expected a non-empty string, got {value!r}")
    return value


LIMIT_NAMES = ("stiffness", "damping", "velocity")
MAX_MASTER_INDEX = 31  # IgH masters are numbered from 0 on one host; more is a slip of the keyboard
MAILBOXES = ("prime", "soem")
MAX_CAN_BITRATE = 1_000_000  # classic CAN's highest rate


def _command_limits(data: dict[str, object], path: Path) -> dict[str, CommandLimits]:
    """``command_limits`` per family; a value the file leaves out is the bundled template's (a robot's file
    written before the section existed still loads, with the product's limits)."""
    limits = data.get("command_limits", {})
    if not isinstance(limits, dict):
        raise ConfigError(path, "command_limits", "expected a mapping family -> limits")
    check_keys(path, "command_limits", limits, FAMILIES)
    template = path == bundled(HARDWARE_FILE)
    defaults = {} if template else load_yaml(bundled(HARDWARE_FILE))["command_limits"]
    result = {}
    for family in FAMILIES:
        key = f"command_limits.{family}"
        section = limits.get(family, {})
        if not isinstance(section, dict):
            raise ConfigError(path, key, "expected a mapping of stiffness, damping, velocity")
        check_keys(path, key, section, LIMIT_NAMES)
        if template and set(section) != set(LIMIT_NAMES):
            raise ConfigError(path, key, "the template must give stiffness, damping and velocity")
        result[family] = CommandLimits(**{
            name: _positive_float(section[name] if name in section else defaults[family][name], path,
                                  f"{key}.{name}") for name in LIMIT_NAMES})
    return result


def _safety(data: dict[str, object], path: Path) -> tuple[float, float]:
    """``safety.collision_margin`` and ``safety.stopping_time``; a value the file leaves out (a file written before
    the section existed) is the template's."""
    safety = data.get("safety", {})
    if not isinstance(safety, dict):
        raise ConfigError(path, "safety", "expected a mapping of collision_margin and stopping_time")
    check_keys(path, "safety", safety, SAFETY_KEYS)
    if path == bundled(HARDWARE_FILE):
        missing = [key for key in SAFETY_KEYS if key not in safety]
        if missing:
            raise ConfigError(path, f"safety.{missing[0]}", "missing", "the template must give every safety value")
    else:
        safety = {**load_yaml(bundled(HARDWARE_FILE))["safety"], **safety}
    values = []
    for key, most, fix in (("collision_margin", MAX_COLLISION_MARGIN_M, "give it in metres, e.g. 0.03 for 3 cm"),
                           ("stopping_time", MAX_STOPPING_TIME_S, "give it in seconds, e.g. 0.2")):
        value = _positive_float(safety[key], path, f"safety.{key}")
        unit = "m" if key == "collision_margin" else "s"
        if value > most:
            raise ConfigError(path, f"safety.{key}", f"{value:g} {unit} is more than {most:g} {unit}", fix)
        values.append(value)
    return values[0], values[1]


def load_hardware(path: str | Path | None = None) -> HardwareConfig:
    """Load and validate a hardware file (default: the bundled one)."""
    path = config_path(path) if path is not None else bundled(HARDWARE_FILE)
    data = load_yaml(path)
    check_keys(path, "", data, ("buses", "joints", "torque_efficiency", "command_limits", "safety"))
    buses = _section(data, path, "buses")
    check_keys(path, "buses", buses, ("ethercat", "can"))
    ec = _section(buses, path, "buses.ethercat")
    can = _section(buses, path, "buses.can")
    check_keys(path, "buses.ethercat", ec, ("interface", "master", "mailbox"))
    check_keys(path, "buses.can", can, ("interface", "channel", "bitrate"))
    ethercat = EthercatBus(
        interface=_str(ec.get("interface"), path, "buses.ethercat.interface"),
        master=_int(ec.get("master", 0), path, "buses.ethercat.master"),
        mailbox=_str(ec.get("mailbox", "prime"), path, "buses.ethercat.mailbox"),
    )
    if ethercat.mailbox not in MAILBOXES:
        raise ConfigError(path, "buses.ethercat.mailbox", f"must be prime or soem, got {ethercat.mailbox!r}",
                          "prime: Prime's CoE layer (the default); soem: SOEM does the mailbox work alone")
    if not 0 <= ethercat.master <= MAX_MASTER_INDEX:
        raise ConfigError(path, "buses.ethercat.master", f"must be 0..{MAX_MASTER_INDEX}, got {ethercat.master}",
                          "the IgH master index, 0 for the first")
    can_bus = CanBus(
        interface=_str(can.get("interface", "socketcan"), path, "buses.can.interface"),
        channel=_str(can.get("channel"), path, "buses.can.channel"),
        bitrate=_int(can.get("bitrate"), path, "buses.can.bitrate"),
    )
    if not 0 < can_bus.bitrate <= MAX_CAN_BITRATE:
        raise ConfigError(path, "buses.can.bitrate", f"must be 1..{MAX_CAN_BITRATE}, got {can_bus.bitrate}",
                          "classic CAN runs at most 1 Mbit/s; the Sito wrists at 1000000")

    joints = _section(data, path, "joints")
    check_keys(path, "joints", joints, ("all_joints", "erob_slaves", "mit_joints", "erob_kt", "erob_gear",
                                     "erob_torque_efficiency", "contact_effort_cap"))
    names = joints.get("all_joints")
    if not isinstance(names, list) or not names:
        raise ConfigError(path, "joints.all_joints", "missing or empty", "list the joints in kinematic order")
    seen: set[str] = set()
    for i, name in enumerate(names):
        _str(name, path, f"joints.all_joints[{i}]")
        if name in seen:
            raise ConfigError(path, f"joints.all_joints[{i}]", f"joint {name!r} is listed twice")
        seen.add(name)

    erob_raw = joints.get("erob_slaves") or {}
    mit_raw = joints.get("mit_joints") or {}
    if not isinstance(erob_raw, dict):
        raise ConfigError(path, "joints.erob_slaves", "expected a mapping joint -> ring position")
    if not isinstance(mit_raw, dict):
        raise ConfigError(path, "joints.mit_joints", "expected a mapping joint -> CAN id")

    erob_slaves: dict[str, int] = {}
    owner_of_ring: dict[int, str] = {}
    for joint, pos in erob_raw.items():
        key = f"joints.erob_slaves.{joint}"
        if joint not in seen:
            raise ConfigError(path, key, f"joint {joint!r} is not in joints.all_joints", "fix the name or add it")
        pos = _int(pos, path, key)
        if pos < 0:
            raise ConfigError(path, key, f"ring position must be >= 0, got {pos}")
        if pos in owner_of_ring:
            raise ConfigError(
                path, key, f"ring position {pos} is already used by {owner_of_ring[pos]}",
                "each eRob has its own ring position",
            )
        owner_of_ring[pos] = joint
        erob_slaves[joint] = pos

    mit_joints: dict[str, int] = {}
    owner_of_id: dict[int, str] = {}
    for joint, can_id in mit_raw.items():
        key = f"joints.mit_joints.{joint}"
        if joint not in seen:
            raise ConfigError(path, key, f"joint {joint!r} is not in joints.all_joints", "fix the name or add it")
        if joint in erob_slaves:
            raise ConfigError(path, key, f"joint {joint!r} is also an eRob", "a joint lives on one bus only")
        can_id = _int(can_id, path, key)
        if can_id not in CAN_ID_RANGE:
            raise ConfigError(path, key, f"CAN id {can_id} is out of range", "use 1..255")
        if can_id in owner_of_id:
            raise ConfigError(path, key, f"CAN id {can_id} is already used by {owner_of_id[can_id]}")
        owner_of_id[can_id] = joint
        mit_joints[joint] = can_id

    for name in names:
        if name not in erob_slaves and name not in mit_joints:
            raise ConfigError(
                path, f"joints.all_joints.{name}", "joint has no bus",
                "give it a ring position in joints.erob_slaves or a CAN id in joints.mit_joints",
            )
    # after the joints with no bus: a ring entry left out is named as such, not as the gap it leaves
    if sorted(owner_of_ring) != list(range(len(owner_of_ring))):
        far = [f"{owner_of_ring[p]}: {p}" for p in sorted(owner_of_ring) if p >= len(owner_of_ring)]
        key = f"joints.erob_slaves.{far[0].split(':')[0]}" if len(far) == 1 else "joints.erob_slaves"
        raise ConfigError(path, key, f"ring positions must be 0..{len(owner_of_ring) - 1}, each once (a ring of "
                          f"{len(owner_of_ring)} eRob has no gaps); beyond it: {', '.join(far)}",
                          "number the eRob in cabling order from 0")

    def per_erob(key: str, default: float) -> dict[str, float]:
        raw = joints.get(key) or {}
        if not isinstance(raw, dict):
            raise ConfigError(path, f"joints.{key}", "expected a mapping joint -> value")
        for joint in raw:
            if joint not in erob_slaves:
                raise ConfigError(path, f"joints.{key}.{joint}", f"{joint!r} is not an eRob joint",
                                  "only joints in joints.erob_slaves take this value")
        return {j: _positive_float(raw.get(j, default), path, f"joints.{key}.{j}") for j in erob_slaves}

    efficiency = _positive_float(data.get("torque_efficiency", 1.0), path, "torque_efficiency")
    if efficiency > 1.0:
        raise ConfigError(path, "torque_efficiency", f"{efficiency} is above 1", "use realised/nominal, 0 < e <= 1")
    erob_efficiency = per_erob("erob_torque_efficiency", efficiency)
    for joint, value in erob_efficiency.items():
        if value > 1.0:
            raise ConfigError(path, f"joints.erob_torque_efficiency.{joint}", f"{value} is above 1",
                              "use realised/nominal, 0 < e <= 1")
    caps = joints.get("contact_effort_cap") or {}
    if not isinstance(caps, dict):
        raise ConfigError(path, "joints.contact_effort_cap", "expected a mapping joint -> Nm")
    for joint in caps:
        if joint not in seen:
            raise ConfigError(path, f"joints.contact_effort_cap.{joint}", f"joint {joint!r} is not in "
                              "joints.all_joints", "fix the name or remove the entry")
    contact_effort_cap = {j: _positive_float(v, path, f"joints.contact_effort_cap.{j}") for j, v in caps.items()}

    command_limits = _command_limits(data, path)
    collision_margin, stopping_time = _safety(data, path)

    return HardwareConfig(
        path=path,
        ethercat=ethercat,
        can=can_bus,
        all_joints=tuple(names),
        erob_slaves=erob_slaves,
        mit_joints=mit_joints,
        erob_kt=per_erob("erob_kt", DEFAULT_KT_NM_PER_MA),
        erob_gear=per_erob("erob_gear", DEFAULT_GEAR),
        torque_efficiency=efficiency,
        command_limits=command_limits,
        erob_torque_efficiency=erob_efficiency,
        contact_effort_cap=contact_effort_cap,
        collision_margin=collision_margin,
        stopping_time=stopping_time,
    )


def write_erob_torque_efficiency(path: str | Path, values: dict[str, float]) -> None:
    """Set ``joints.erob_torque_efficiency`` of ``values``' joints in the hardware file at ``path``, keeping every
    other line (and comment) as it is and the joints' earlier values; atomic, and checked by loading the result
    before it replaces the file."""
    import tempfile

    import yaml

    from humanoid_prime.files import atomic_write_text

    path = config_path(path)
    current = load_hardware(path)
    unknown = sorted(set(values) - set(current.erob_slaves))
    if unknown:
        raise ConfigError(path, "joints.erob_torque_efficiency", f"{', '.join(unknown)} is not an eRob joint")
    data = load_yaml(path)
    merged = dict((data.get("joints") or {}).get("erob_torque_efficiency") or {})
    merged.update(values)
    lines = path.read_text().splitlines(keepends=True)
    top = next((k for k, line in enumerate(lines) if line.rstrip() == "joints:"), None)
    if top is None:
        raise ConfigError(path, "joints", "no top-level 'joints:' line to add erob_torque_efficiency under",
                          "write the joints section in block style")
    section = [k for k in range(top + 1, len(lines)) if lines[k].strip() and not lines[k].lstrip().startswith("#")]
    end = next((k for k in section if not lines[k][0].isspace()), len(lines))
    children = [k for k in section if k < end]
    indent = (len(lines[children[0]]) - len(lines[children[0]].lstrip())) if children else 2
    pad = " " * indent
    block = [f"{pad}erob_torque_efficiency:\n"] + [f"{pad}  {joint}: {value!r}\n" for joint, value in merged.items()]
    found = next((k for k in children if lines[k].startswith(f"{pad}erob_torque_efficiency:")), None)
    if found is None:
        lines[top + 1:top + 1] = block
    else:
        stop = found + 1
        while stop < end and (not lines[stop].strip() or len(lines[stop]) - len(lines[stop].lstrip()) > indent):
            stop += 1
        while stop > found + 1 and not lines[stop - 1].strip():  # blank lines after the block stay
            stop -= 1
        lines[found:stop] = block
    text = "".join(lines)
    check = yaml.safe_load(text)["joints"]["erob_torque_efficiency"]
    if check != merged:
        raise ConfigError(path, "joints.erob_torque_efficiency", "could not be rewritten in place",
                          "set the values by hand")
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=True) as trial:
        trial.write(text)
        trial.flush()
        load_hardware(trial.name)  # the whole file still loads, or nothing is written
    atomic_write_text(path, text)
