"""The robot description ``prime_dummy``: xacro -> URDF, joint limits, and its ros2_control blocks."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from humanoid_prime.config.hardware import HardwareConfig
from humanoid_prime.config.urdf_cache import expand_cached
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import bundled

if TYPE_CHECKING:
    from xml.dom import minidom

XACRO_FILE = "description/prime_dummy.urdf.xacro"
COMMAND_INTERFACES = ("position", "velocity", "effort", "stiffness", "damping")
STATE_INTERFACES = ("position", "velocity", "effort")

ETHERCAT_BLOCK = "PrimeEtherCATSide"
SITO_BLOCK = "PrimeSitoCAN"
MUJOCO_BLOCK = "MujocoSystem"
# The buses a run brings up, by the --backends name, as the description's hardware blocks.
BACKEND_BLOCKS: dict[str, tuple[str, ...]] = {
    "all": (ETHERCAT_BLOCK, SITO_BLOCK),
    "ec": (ETHERCAT_BLOCK,),
    "can": (SITO_BLOCK,),
}


@dataclass(frozen=True)
class JointLimits:
    lower: float
    upper: float
    effort: float
    velocity: float


@dataclass(frozen=True)
class HardwareBlock:
    """One ``<ros2_control>`` block: which plugin owns which joints, with their parameters."""

    name: str
    plugin: str
    params: dict[str, str]
    joints: tuple[str, ...]
    joint_params: dict[str, dict[str, str]]


@dataclass(frozen=True)
class Description:
    urdf: str
    source: Path
    limits: dict[str, JointLimits]
    blocks: tuple[HardwareBlock, ...]

    def block(self, name: str) -> HardwareBlock:
        for block in self.blocks:
            if block.name == name:
                return block
        raise KeyError(name)


def render_urdf(hardware: HardwareConfig, *, use_sim: bool = False, control_frequency: float = 50.0,
                erob_config_dir: str | Path = "erob_config", xacro_file: str | Path | None = None) -> str:
    """Expand the xacro into URDF text; the ros2_control section comes from the hardware file. Cached in the
    user's cache folder (``urdf_cache``) while the files it reads are unchanged."""
    source = Path(xacro_file) if xacro_file is not None else bundled(XACRO_FILE)
    mappings = {
        "hardware_file": str(hardware.path),
        "use_sim": "true" if use_sim else "false",
        "control_frequency": f"{control_frequency:g}",
        "erob_config_dir": str(erob_config_dir),
    }

    def expand() -> str:
        import xacro

        try:
            doc: minidom.Document = xacro.process_file(str(source), mappings=mappings)
        except Exception as exc:  # xacro raises plain Exceptions with the useful text
            raise ConfigError(source, "", f"xacro failed: {exc}") from None
        return doc.toprettyxml(indent="  ")

    return expand_cached(source, mappings, expand)


def parse_urdf(urdf: str, source: Path) -> tuple[dict[str, JointLimits], tuple[HardwareBlock, ...]]:
    root = ET.fromstring(urdf)
    limits: dict[str, JointLimits] = {}
    for joint in root.findall("joint"):
        if joint.get("type") not in ("revolute", "prismatic"):
            continue
        name = joint.get("name", "")
        limit = joint.find("limit")
        if limit is None:
            raise ConfigError(source, f"joint {name}", "actuated joint has no <limit>",
                              "add lower/upper/effort/velocity")
        try:
            limits[name] = JointLimits(*(float(limit.get(k, "nan")) for k in ("lower", "upper", "effort", "velocity")))
        except ValueError:
            raise ConfigError(source, f"joint {name}.limit", "limit values are not numbers") from None
        lim = limits[name]
        if not lim.lower < lim.upper:
            raise ConfigError(source, f"joint {name}.limit", f"lower {lim.lower} is not below upper {lim.upper}")
    blocks = []
    for rc in root.findall("ros2_control"):
        hw = rc.find("hardware")
        plugin = hw.findtext("plugin", "").strip() if hw is not None else ""
        params = {p.get("name", ""): (p.text or "").strip() for p in (hw.findall("param") if hw is not None else [])}
        names: list[str] = []
        joint_params: dict[str, dict[str, str]] = {}
        for j in rc.findall("joint"):
            name = j.get("name", "")
            commands = tuple(c.get("name") for c in j.findall("command_interface"))
            states = tuple(s.get("name") for s in j.findall("state_interface"))
            if commands != COMMAND_INTERFACES or states != STATE_INTERFACES:
                raise ConfigError(source, f"ros2_control {rc.get('name')}.{name}",
                                  f"interfaces {commands}/{states} are not the MIT surface",
                                  f"declare command {COMMAND_INTERFACES} and state {STATE_INTERFACES}")
            jp = {p.get("name", ""): (p.text or "").strip() for p in j.findall("param")}
            module = j.find("ec_module")
            if module is not None:
                jp.update({p.get("name", ""): (p.text or "").strip() for p in module.findall("param")})
                jp["ec_plugin"] = module.findtext("plugin", "").strip()
            names.append(name)
            joint_params[name] = jp
        blocks.append(HardwareBlock(rc.get("name", ""), plugin, params, tuple(names), joint_params))
    return limits, tuple(blocks)


def load_description(hardware: HardwareConfig, *, use_sim: bool = False, control_frequency: float = 50.0,
                     erob_config_dir: str | Path = "erob_config",
                     xacro_file: str | Path | None = None) -> Description:
    """Render and check the description against the hardware file: same joints, each owned once."""
    source = Path(xacro_file) if xacro_file is not None else bundled(XACRO_FILE)
    urdf = render_urdf(hardware, use_sim=use_sim, control_frequency=control_frequency,
                       erob_config_dir=erob_config_dir, xacro_file=source)
    limits, blocks = parse_urdf(urdf, source)
    described, declared = set(limits), set(hardware.all_joints)
    if described != declared:
        only_desc = sorted(described - declared)
        only_hw = sorted(declared - described)
        raise ConfigError(source, "joints",
                          f"description and {hardware.path.name} name different joints "
                          f"(only in description: {only_desc or 'none'}; only in hardware file: {only_hw or 'none'})",
                          "make joints.all_joints match the description's actuated joints")
    owner: dict[str, str] = {}
    for block in blocks:
        for joint in block.joints:
            if joint in owner:
                raise ConfigError(source, f"ros2_control {block.name}.{joint}",
                                  f"joint is also owned by {owner[joint]}", "each joint belongs to one block")
            owner[joint] = block.name
    missing = [j for j in hardware.all_joints if j not in owner]
    if missing:
        raise ConfigError(source, "ros2_control", f"joints without a hardware block: {missing}")
    return Description(urdf=urdf, source=source, limits=limits, blocks=blocks)
