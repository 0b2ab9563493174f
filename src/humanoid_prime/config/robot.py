"""Prime as the rest of the stack sees it: the canonical joint list with family, address and limits."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from humanoid_prime.config.description import Description, load_description
from humanoid_prime.config.hardware import HardwareConfig, load_hardware

if TYPE_CHECKING:  # numpy is imported where the arrays are made: reading the robot (`prime info`) needs none
    import numpy as np
    import numpy.typing as npt

Family = Literal["erob", "sito"]


@dataclass(frozen=True)
class JointSpec:
    index: int
    name: str
    family: Family
    ring_position: int | None
    can_id: int | None
    lower: float
    upper: float
    effort_limit: float
    velocity_limit: float

    @property
    def bus(self) -> str:
        return "ethercat" if self.family == "erob" else "can"

    @property
    def address(self) -> str:
        return f"ring {self.ring_position}" if self.family == "erob" else f"id {self.can_id}"


@dataclass(frozen=True)
class Robot:
    hardware: HardwareConfig
    description: Description
    joints: tuple[JointSpec, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    @property
    def n(self) -> int:
        return len(self.joints)

    def index(self, name: str) -> int:
        for joint in self.joints:
            if joint.name == name:
                return joint.index
        raise KeyError(f"unknown joint {name!r}; known joints: {', '.join(self.names)}")

    def indices(self, family: Family) -> npt.NDArray[np.intp]:
        import numpy as np

        return np.array([j.index for j in self.joints if j.family == family], dtype=np.intp)

    @property
    def lower(self) -> npt.NDArray[np.float64]:
        import numpy as np

        return np.array([j.lower for j in self.joints])

    @property
    def upper(self) -> npt.NDArray[np.float64]:
        import numpy as np

        return np.array([j.upper for j in self.joints])

    @property
    def effort_limit(self) -> npt.NDArray[np.float64]:
        import numpy as np

        return np.array([j.effort_limit for j in self.joints])


def build_robot(hardware: HardwareConfig, description: Description) -> Robot:
    specs = []
    for i, name in enumerate(hardware.all_joints):
        lim = description.limits[name]
        erob = name in hardware.erob_slaves
        specs.append(JointSpec(
            index=i,
            name=name,
            family="erob" if erob else "sito",
            ring_position=hardware.erob_slaves.get(name),
            can_id=hardware.mit_joints.get(name),
            lower=lim.lower,
            upper=lim.upper,
            effort_limit=lim.effort,
            velocity_limit=lim.velocity,
        ))
    return Robot(hardware=hardware, description=description, joints=tuple(specs))


def load_robot(hardware_file: str | Path | None = None, *, use_sim: bool = False,
               control_frequency: float = 50.0) -> Robot:
    """Load the hardware file and the description and check they agree."""
    hardware = load_hardware(hardware_file)
    description = load_description(hardware, use_sim=use_sim, control_frequency=control_frequency)
    return build_robot(hardware, description)
