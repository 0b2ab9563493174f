"""Where a robot's configuration lives: one rule for every command.

Each of the three files (hardware, calibration, controllers) is, in this order:
1. the file given on the command line (``--hardware``, ``--calibration``, ``--controllers``);
2. the file of that name in the robot's config folder: ``$PRIME_CONFIG_DIR``, else
   ``$XDG_CONFIG_HOME/prime`` (``~/.config/prime``), with a ``NAME`` subfolder for ``--robot NAME``
   (or ``$PRIME_ROBOT``) where a lab has several Primes;
3. the bundled template, read-only, when the default folder has no such file.

Something of that name in the folder that is not a readable file (a folder, a broken symlink) is refused, never
passed over for the template: the robot would run on the template's offsets.

A folder the user named (``--robot``, ``$PRIME_ROBOT``, ``$PRIME_CONFIG_DIR``) must exist: ``prime config
init`` creates it, so a misspelt robot never runs on the templates. Commands that write a file (calibrate,
flip, ``config init``) write into the robot's folder, never inside the installed package.
"""

from __future__ import annotations

import hashlib
import os
import re
import stat
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from humanoid_prime.errors import ConfigError, PrimeError
from humanoid_prime.files import bundled, check_not_package

CONFIG_DIR_ENV = "PRIME_CONFIG_DIR"
ROBOT_ENV = "PRIME_ROBOT"
KINDS = ("hardware", "calibration", "controllers")
FILE_NAMES = {"hardware": "prime_hardware.yaml", "calibration": "prime_calibration.yaml",
              "controllers": "prime_controllers.yaml"}
ROBOT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


@dataclass(frozen=True)
class RobotFolder:
    """The robot's config folder, and in words where that choice came from."""

    path: Path
    why: str
    named: bool  # the user named it (it must exist to be read)
    robot: str | None

    @property
    def state(self) -> Path:
        """Where commands keep what they must remember about this robot between runs (created when written)."""
        return self.path / "state"

    def init_command(self) -> str:
        return "prime config init" + (f" --robot {self.robot}" if self.robot else "")

    def check_exists(self) -> None:
        if os.path.lexists(self.path) and not self.path.is_dir():
            raise PrimeError(f"the configuration folder {self.path} ({self.why}) is {_not_a_file(self.path)}; "
                             f"move it away, then `{self.init_command()}`")
        if self.named and not self.path.is_dir():
            raise PrimeError(f"no configuration folder {self.path} ({self.why}); create it with "
                             f"`{self.init_command()}`, or check the name")

    def own_file(self, kind: str) -> Path | None:
        """The folder's file of ``kind`` if it has one, None if nothing of that name is there; anything else of
        that name (a folder, a broken symlink, a device) is a ConfigError that says what it is."""
        path = self.path / FILE_NAMES[kind]
        if path.is_file():
            return path
        if not os.path.lexists(path):
            return None
        fix = "point it at the file, or remove it" if path.is_symlink() else "move it away"
        raise ConfigError(path, "", f"is {_not_a_file(path)}, not the robot's {kind} file",
                          f"{fix}; `{self.init_command()}` then writes the template there")


def _not_a_file(path: Path) -> str:
    """What ``path``, which exists but is no regular file, is instead."""
    if path.is_symlink():
        try:
            os.stat(path)
        except OSError as exc:
            return f"a broken symlink to {os.readlink(path)} ({exc.strerror})"
    if path.is_dir():
        return "a folder"
    try:
        kind = stat.S_IFMT(os.stat(path).st_mode)
    except OSError as exc:
        return f"unreadable ({exc.strerror})"
    return {stat.S_IFIFO: "a named pipe", stat.S_IFSOCK: "a socket", stat.S_IFCHR: "a device",
            stat.S_IFBLK: "a device"}.get(kind, "not a regular file")


def robot_folder(robot: str | None = None) -> RobotFolder:
    """The config folder of ``robot`` (None: ``$PRIME_ROBOT``, else the default folder itself, no subfolder)."""
    source = "--robot"
    if robot is None and os.environ.get(ROBOT_ENV):
        robot, source = os.environ[ROBOT_ENV], f"${ROBOT_ENV}"
    if robot is not None and not ROBOT_NAME.fullmatch(robot):
        raise PrimeError(f"{source} {robot!r}: a robot name is letters, digits, '.', '_' or '-' (up to 64), "
                         "starting with a letter or digit")
    if os.environ.get(CONFIG_DIR_ENV):
        base, why, named = Path(os.environ[CONFIG_DIR_ENV]).expanduser(), f"${CONFIG_DIR_ENV}", True
    elif os.environ.get("XDG_CONFIG_HOME"):
        base, why, named = Path(os.environ["XDG_CONFIG_HOME"]).expanduser() / "prime", "$XDG_CONFIG_HOME/prime", False
    else:
        base, why, named = Path.home() / ".config" / "prime", "~/.config/prime", False
    if robot is not None:
        return RobotFolder(base.absolute() / robot, f"robot {robot!r} ({source}) in {why}", True, robot)
    return RobotFolder(base.absolute(), why, named, None)


@dataclass(frozen=True)
class ConfigFile:
    """One configuration file a command uses: where it is and why that one."""

    kind: str  # hardware | calibration | controllers
    path: Path
    why: str
    template: bool  # the bundled, read-only template

    def sha256(self) -> str:
        try:
            return hashlib.sha256(self.path.read_bytes()).hexdigest()
        except OSError:
            return ""

    def as_dict(self) -> dict[str, object]:
        return {"path": str(self.path), "sha256": self.sha256(), "source": self.why, "template": self.template}


def template(kind: str) -> Path:
    return bundled(FILE_NAMES[kind])


def resolve(kind: str, given: str | Path | None, folder: RobotFolder) -> ConfigFile:
    """The file of ``kind`` a command reads (module docstring)."""
    if given is not None:
        return ConfigFile(kind, Path(given).expanduser().absolute(), f"--{kind}", template=False)
    folder.check_exists()
    path = folder.own_file(kind)
    if path is not None:
        return ConfigFile(kind, path, folder.why, template=False)
    return ConfigFile(kind, template(kind), f"bundled template (no {FILE_NAMES[kind]} in {folder.path})",
                      template=True)


def write_target(config: ConfigFile, folder: RobotFolder) -> Path:
    """Where a command that rewrites ``config`` writes: the file itself, or for a template the robot's own copy
    in its folder (created on the way)."""
    path = folder.path / FILE_NAMES[config.kind] if config.template else config.path
    check_not_package(path, f"the {config.kind} file")
    return path


@dataclass(frozen=True)
class ConfigFiles:
    """The three files of a run, resolved once; every run names them (path and sha256) in its reports."""

    folder: RobotFolder
    hardware: ConfigFile
    calibration: ConfigFile
    controllers: ConfigFile

    def __iter__(self) -> Iterator[ConfigFile]:
        return iter((self.hardware, self.calibration, self.controllers))

    def as_dict(self) -> dict[str, dict[str, object]]:
        return {c.kind: c.as_dict() for c in self}

    def lines(self) -> list[str]:
        """One line per file, for a run's header: kind, path, the start of its sha256."""
        return [f"{c.kind:<11} {c.path}  sha256 {c.sha256()[:12]}{'  (template)' if c.template else ''}"
                for c in self]


def resolve_all(robot: str | None = None, *, hardware: str | Path | None = None,
                calibration: str | Path | None = None, controllers: str | Path | None = None) -> ConfigFiles:
    folder = robot_folder(robot)
    given = {"hardware": hardware, "calibration": calibration, "controllers": controllers}
    return ConfigFiles(folder, *(resolve(kind, given[kind], folder) for kind in KINDS))
