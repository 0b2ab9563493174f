"""What a gain override changed on an eRob, kept on disk until it is undone.

A ``GainOverride`` (``prime limp``) restores the drive on every exit path its process runs; SIGKILL, the OOM
killer or a host that lost power run none, and the drive stays limp (gate 1, pos_reg 0) in its memory. So the
override first writes a record: which drive, what it held (gate, the three gain registers, any further object
set), who changed it and how the ring was reached; only then does it weaken the drive, and it removes the record
once the drive is restored. The next command that reaches the ring the same way finds a record whose writer is
gone, restores the drive from it, and says so.

The registers alone could not say it: a drive limp under a running ``prime limp`` and one whose ``prime limp`` was
killed read the same, and neither says what the drive held before. A record names its writer by pid and start
time (a pid the kernel gave to another process since is told apart), and the ring by the way it was reached (the
control socket of the run that owns the master, or an IgH master), so a record is never applied to a drive it was
not made on through another run's socket. Records live in the robot's state folder, one file per drive and way,
each written atomically.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_text

FORMAT = 1
REGISTERS = ("gate", "pos_reg", "vel_reg", "integral")


def process_start(pid: int) -> int | None:
    """When process ``pid`` started (clock ticks after boot, /proc/PID/stat field 22), None if there is none."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[19])  # the fields after the command name start at field 3


@dataclass(frozen=True)
class OverrideRecord:
    """One drive's override as its writer recorded it before the first write."""

    path: Path  # the record's own file
    position: int
    joint: str
    found: dict[str, int]  # REGISTERS as the override found them
    objects: dict[tuple[int, int], int]  # further objects it set, as found
    left_as: str  # how the drive is while overridden, in words ("limp")
    command: str
    pid: int
    started: int | None
    written_at: float  # seconds since the epoch

    @property
    def writer_running(self) -> bool:
        return self.started is not None and process_start(self.pid) == self.started

    def describe(self) -> str:
        """Who left the drive how, in words."""
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.written_at))
        return (f"ring {self.position} ({self.joint}) was left {self.left_as} by `{self.command}` (pid {self.pid}, "
                f"{since}), which ended without restoring it")


class OverrideJournal:
    """The records of the overrides made one way (``via``: the control socket, or the IgH master) on the robot
    whose state folder is ``folder``; ``command`` names the writer in the records it writes."""

    def __init__(self, folder: Path, via: str, command: str = "") -> None:
        self.folder = folder
        self.via = via
        self.command = command

    def _path(self, position: int) -> Path:
        way = hashlib.sha256(self.via.encode()).hexdigest()[:8]
        return self.folder / f"erob-ring{position}-gains-{way}.json"

    def record(self, position: int, joint: str, found: dict[str, int], objects: dict[tuple[int, int], int],
               left_as: str) -> None:
        """Written before the override's first write; raises PrimeError (nothing written to the drive) if the
        record cannot be kept."""
        document = {"format": FORMAT, "via": self.via, "position": position, "joint": joint,
                    "found": {name: found[name] for name in REGISTERS},
                    "objects": [[index, sub, value] for (index, sub), value in objects.items()],
                    "left_as": left_as, "command": self.command, "pid": os.getpid(),
                    "started": process_start(os.getpid()), "written_at": time.time()}
        try:
            atomic_write_text(self._path(position), json.dumps(document, indent=2) + "\n")
        except PrimeError as exc:
            raise PrimeError(f"ring {position}: the drive is left as it is, since a record of its gains could not "
                             f"be kept first ({exc})") from None

    def clear(self, position: int) -> None:
        """The drive is restored: its record goes."""
        self._path(position).unlink(missing_ok=True)

    def left(self) -> list[OverrideRecord]:
        """The records made this way whose writer is gone, by ring position."""
        records = [self._read(path) for path in sorted(self.folder.glob("erob-ring*-gains-*.json"))]
        return sorted((r for r in records if r is not None and not r.writer_running), key=lambda r: r.position)

    def _read(self, path: Path) -> OverrideRecord | None:
        try:
            document = json.loads(path.read_text())
            if document.get("via") != self.via:
                return None
            return OverrideRecord(
                path, int(document["position"]), str(document["joint"]),
                {name: int(document["found"][name]) for name in REGISTERS},
                {(int(index), int(sub)): int(value) for index, sub, value in document["objects"]},
                str(document["left_as"]), str(document["command"]), int(document["pid"]),
                None if document["started"] is None else int(document["started"]), float(document["written_at"]))
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise PrimeError(f"{path}: a record of a drive's gains that cannot be read ({exc}); check that drive's "
                             "gate and gains (prime ec sdo read RING 0x2383:0), then remove the file") from None
