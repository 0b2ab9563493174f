"""The emulator's tunables, shared by the command line, the harness and the ring."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field, fields

from humanoid_prime.virtual.ring.quirks import PROFILES, Quirks

# 350 process-data cycles to DC lock: a 50 Hz bring-up loop needs 7 s per slave (the ROS 2 original's
# figure), a 1 kHz loop 0.35 s.
DEFAULT_DC_LOCK_CYCLES = 350
PLANTS = ("inertia", "mujoco")


def _option(default: float | int | str, text: str) -> object:
    return field(default=default, metadata={"help": text})


@dataclass
class RingOptions:
    slaves: int = _option(10, "number of eRob drives on the ring")
    dc_lock_cycles: int = _option(
        DEFAULT_DC_LOCK_CYCLES, "process-data frames carrying the DC time distribution a slave needs after SYNC0 "
                                "starts before it accepts SAFE-OP -> OP")
    sync_tolerance: float = _option(
        0.2, "a frame interval above SYNC0 cycle * (1 + this) counts as SYNC0 outrunning the frames (restarts "
             "the lock; in OP, sync_fault_cycles in a row fault the drive)")
    dc_sync_window_ns: int = _option(
        10_000, "largest difference (0x092C) between a slave's system time and the reference clock's at which its "
                "SYNC0 counts as in step with the ring: a frame further off restarts the lock, and counts towards "
                "sync_fault_cycles in OP (10 us: what IgH's master waits for before starting SYNC0)")
    sync_fault_cycles: int = _option(5, "consecutive too-long frame intervals, or frames off the ring's time, that "
                                        "fault a drive in OP")
    mailbox_latency_s: float = _option(0.0005, "time from an SDO request to its reply in the read mailbox")
    mailbox_jitter_s: float = _option(0.0, "each reply waits up to this much longer still, uniformly at random (a "
                                           "drive whose firmware is busy)")
    mailbox_burst_s: float = _option(0.0, "how much later each reply of a burst comes (a drive, or a host, stalled "
                                          "for a while)")
    mailbox_burst_chance: float = _option(0.0, "chance that a reply starts a burst of mailbox_burst_replies slow "
                                               "replies")
    mailbox_burst_replies: int = _option(5, "replies in a burst")
    stall_interval_s: float = _option(0.0, "mean time between stalls of the whole emulator, drawn at random (0: "
                                           "none): it answers no frame for stall_s, then every frame that waited, "
                                           "as a process a busy host did not schedule")
    stall_s: float = _option(0.02, "how long each of those stalls lasts")
    seed: int = _option(0, "seed of the random draws (jitter, bursts, stalls)")
    mailbox_size: int = _option(128, "bytes of each mailbox (SM0/SM1)")
    state_change_s: float = _option(0.0, "time the firmware takes to carry out a request for PRE-OP or SAFE-OP from a "
                                         "lower state (its AL status shows the old state meanwhile)")
    physics_dt_s: float = _option(0.001, "integration step of drives and plant")
    hop_delay_ns: int = _option(700, "frame delay per slave, as latched in the DC receive-time registers")
    plant: str = _option("inertia", "mechanics: inertia (one joint per drive) or mujoco (Prime's arms, bundled "
                                    "hardware and calibration files; needs one slave per joints.erob_slaves entry)")
    gain_bytes: int = _option(2, "bytes the loop-gain objects 0x2381/0x2382 hold, enforced on write: 2 as ZeroErr's "
                                 "EDS declares them, 4 as one public host reads them")
    rated_torque_mnm: int = _option(23000, "0x6076 rated torque in mN*m (23000 nominal eRob70 50:1; an eRob80H120I "
                                           "reads 31000)")
    quirks: str = _option("", "quirk profiles of real slaves, comma-separated, or all: " + ", ".join(PROFILES))

    def check(self) -> None:
        """Raise ValueError naming the first option out of range."""
        if not 1 <= self.slaves <= 64:
            raise ValueError(f"slaves must be 1..64, got {self.slaves}")
        if self.dc_lock_cycles < 0:
            raise ValueError(f"dc_lock_cycles must be >= 0, got {self.dc_lock_cycles}")
        if not 0 <= self.sync_tolerance < 10:
            raise ValueError(f"sync_tolerance must be in [0, 10), got {self.sync_tolerance}")
        if not 0 < self.dc_sync_window_ns <= 0x7FFFFFFF:
            raise ValueError(f"dc_sync_window_ns must be 1..{0x7FFFFFFF}, got {self.dc_sync_window_ns}")
        if self.sync_fault_cycles < 1:
            raise ValueError(f"sync_fault_cycles must be >= 1, got {self.sync_fault_cycles}")
        if not 0 <= self.mailbox_latency_s < 1:
            raise ValueError(f"mailbox_latency_s must be in [0, 1), got {self.mailbox_latency_s}")
        for name in ("mailbox_jitter_s", "mailbox_burst_s", "stall_s"):
            if not 0 <= getattr(self, name) < 1:
                raise ValueError(f"{name} must be in [0, 1), got {getattr(self, name)}")
        if not 0 <= self.mailbox_burst_chance <= 1:
            raise ValueError(f"mailbox_burst_chance must be in [0, 1], got {self.mailbox_burst_chance}")
        if not 1 <= self.mailbox_burst_replies <= 1000:
            raise ValueError(f"mailbox_burst_replies must be 1..1000, got {self.mailbox_burst_replies}")
        if not (self.stall_interval_s == 0 or 0.01 <= self.stall_interval_s <= 3600):
            raise ValueError(f"stall_interval_s must be 0 (no stalls) or 0.01..3600, got {self.stall_interval_s}")
        if not 0 <= self.state_change_s <= 10:
            raise ValueError(f"state_change_s must be in [0, 10], got {self.state_change_s}")
        if not 32 <= self.mailbox_size <= 1024:
            raise ValueError(f"mailbox_size must be 32..1024 bytes, got {self.mailbox_size}")
        if not 1e-5 <= self.physics_dt_s <= 0.01:
            raise ValueError(f"physics_dt_s must be 1e-5..0.01, got {self.physics_dt_s}")
        if not 0 <= self.hop_delay_ns <= 1_000_000:
            raise ValueError(f"hop_delay_ns must be 0..1000000, got {self.hop_delay_ns}")
        if self.plant not in PLANTS:
            raise ValueError(f"plant must be one of {', '.join(PLANTS)}, got {self.plant!r}")
        if self.gain_bytes not in (2, 4):
            raise ValueError(f"gain_bytes must be 2 or 4, got {self.gain_bytes}")
        if not 1 <= self.rated_torque_mnm <= 1_000_000:
            raise ValueError(f"rated_torque_mnm must be 1..1000000, got {self.rated_torque_mnm}")
        Quirks.parse(self.quirks)

    @property
    def quirk_profiles(self) -> Quirks:
        return Quirks.parse(self.quirks)

    def to_args(self) -> list[str]:
        """Command-line arguments that reproduce these options."""
        out = []
        for f in fields(self):
            out += ["--" + f.name.replace("_", "-"), str(getattr(self, f.name))]
        return out

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        defaults = RingOptions()
        for f in fields(RingOptions):
            default = getattr(defaults, f.name)
            parser.add_argument("--" + f.name.replace("_", "-"), type=type(default), default=default,
                                metavar="NAME,..." if isinstance(default, str) else type(default).__name__.upper(),
                                help=f"{f.metadata['help']} (default {default})")

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> RingOptions:
        options = cls(**{f.name: getattr(args, f.name) for f in fields(cls)})
        options.check()
        return options
