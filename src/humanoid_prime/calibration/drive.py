"""The moving eRob's drive during a hands-free approach (``calibration.auto``): the approach gains in its loop-gain
registers (gate, changed-only writes in the never-stiffer order), a following-error window wide enough for them,
and its own torque limit (0x6072) lowered to what the approach needs where it has one; all restored as found.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

from humanoid_prime.calibration.approach import JointRun
from humanoid_prime.calibration.limp import GainOverride
from humanoid_prime.config.robot import Robot
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD, RATED_TORQUE_NM
from humanoid_prime.drivers.erob.gains import ErobRegisters, registers_to_gains
from humanoid_prime.drivers.erob.objects import FOLLOWING_ERROR_WINDOW, MAX_TORQUE, RATED_TORQUE
from humanoid_prime.drivers.ethercat.sdo_client import SdoClient, SizedSdo
from humanoid_prime.errors import PrimeError

DRIVE_LIMIT_MARGIN = 1.25  # the drive's own torque limit over the most the approach asks of it
TORQUE_LIMIT = (MAX_TORQUE, 0x00)
WINDOW = (FOLLOWING_ERROR_WINDOW, 0x00)


class ApproachOverride(GainOverride):
    """The approach ``registers`` with a following-error window of at least ``window`` counts and the drive's own
    torque limit at most ``torque_limit`` per mille (never raised, never narrowed from what the drive holds)."""

    def __init__(self, sdo: SdoClient, position: int, registers: ErobRegisters, window: int,
                 torque_limit: int) -> None:
        super().__init__(sdo, position, registers, objects={WINDOW: window}, optional={TORQUE_LIMIT: torque_limit})
        self.window = window
        self.torque_limit = torque_limit

    def __enter__(self) -> ApproachOverride:
        objects = self.objects
        with contextlib.suppress(PrimeError):
            self.extra[WINDOW] = max(objects.read(self.position, WINDOW), self.window)
        try:
            self.torque_limit = min(objects.read(self.position, TORQUE_LIMIT), self.torque_limit)
            self.optional[TORQUE_LIMIT] = self.torque_limit
        except PrimeError:
            pass
        super().__enter__()
        return self


@contextlib.contextmanager
def approach_drive(robot: Robot, joint: str, run: JointRun, registers: ErobRegisters,
                   ring: tuple[SdoClient, int]) -> Iterator[str]:
    """``joint``'s drive set for ``run`` for the block; yields what became of its own torque limit, in words."""
    sdo, position = ring
    hardware = robot.hardware
    kp_nominal, _ = registers_to_gains(registers, kt=hardware.erob_kt[joint], gear=hardware.erob_gear[joint])
    # The most effort the approach asks: the gravity along the travel, the anchor's offset from it, the cap.
    most = run.weight + abs(run.anchor - run.gravity0) + run.cap
    window = math.ceil(2.0 * most / kp_nominal * COUNTS_PER_RAD)
    try:
        rated = SizedSdo(sdo).read(position, (RATED_TORQUE, 0)) / 1000.0 or RATED_TORQUE_NM
    except PrimeError:
        rated = RATED_TORQUE_NM
    override = ApproachOverride(sdo, position, registers, window, math.ceil(DRIVE_LIMIT_MARGIN * most / rated * 1000.0))
    with override:
        if TORQUE_LIMIT in override.missing:
            yield f"none: the drive has no 0x6072 ({override.missing[TORQUE_LIMIT]})"
        else:
            yield (f"0x6072 {override.torque_limit} per mille of {rated:g} Nm "
                   f"({override.torque_limit * rated / 1000.0:.2f} Nm) while it moved, then "
                   f"{override.extra_snapshot[TORQUE_LIMIT]} again")
