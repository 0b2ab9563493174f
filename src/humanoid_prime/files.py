"""Reading YAML with errors that name the file, and atomic writes that never leave a half file."""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from humanoid_prime.errors import ConfigError


def bundled(name: str) -> Path:
    """Path of a file shipped in the package's data folder (e.g. ``prime_hardware.yaml``)."""
    return Path(str(resources.files("humanoid_prime") / "data" / name))


def load_yaml(path: str | Path) -> Any:
    """Parse a YAML file; a missing, unreadable or malformed file raises ConfigError naming it."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found", "check the path") from None
    except OSError as exc:
        raise ConfigError(path, "", f"cannot read: {exc.strerror}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or "invalid YAML"
        raise ConfigError(path, where, f"malformed YAML: {problem}", "fix the syntax") from None


def output_problem(path: str | Path, *, directory: bool = False) -> str | None:
    """Why ``path`` could not be written as an output file (or, with ``directory``, filled as an output
    folder), or None. Checked before a run starts, so a run's result is never lost at its end."""
    path = Path(path).expanduser()
    if directory:
        if path.exists() and not path.is_dir():
            return f"{path} is a file, not a folder"
    elif path.is_dir():
        return f"{path} is a folder; give a file name"
    elif path.exists() and not os.access(path, os.W_OK):
        return f"{path} is read-only"
    folder = (path if directory else path.parent).absolute()
    while not folder.exists():  # missing folders are created on write, under the first one that exists
        folder = folder.parent
    if not folder.is_dir():
        return f"{folder} is a file, so {path} cannot be created"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"cannot write in {folder}"
    return None


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` atomically (see ``atomic_write_bytes``)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the complete new one, never a part.

    The data goes to a temporary file in the same folder, is flushed to disk, and is renamed over
    the target; a failure or interruption at any point leaves the previous file untouched. The file
    keeps the mode of the one it replaces; a new file gets the mode the umask gives.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
    except FileNotFoundError:
        mode = 0o666 & ~_umask()
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fchmod(handle.fileno(), mode)
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def _umask() -> int:
    current = os.umask(0)
    os.umask(current)
    return current


def atomic_write_yaml(path: str | Path, data: Any, header: str = "") -> None:
    """Dump ``data`` as block-style YAML (keys in insertion order) and write it atomically."""
    body = yaml.safe_dump(data, sort_keys=False, default_flow_style=False)
    atomic_write_text(path, header + body)
