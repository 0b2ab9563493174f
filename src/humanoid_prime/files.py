"""Reading YAML with errors that name the file, and atomic writes that never leave a half file."""

from __future__ import annotations

import contextlib
import difflib
import os
import stat
import tempfile
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from humanoid_prime.errors import ConfigError, PrimeError


def bundled(name: str) -> Path:
    """Path of a file shipped in the package's data folder (e.g. ``prime_hardware.yaml``)."""
    return Path(str(resources.files("humanoid_prime") / "data" / name))


def package_root() -> Path:
    """The installed package's own folder (its code and templates): nothing is ever written under it."""
    return Path(__file__).resolve().parent


def inside_package(path: str | Path) -> bool:
    target = Path(path).expanduser().absolute().resolve()
    return target == package_root() or package_root() in target.parents


def check_not_package(path: str | Path, what: str = "this file") -> None:
    """Refuse to write ``path`` when it lies inside the installed package (its templates are read-only)."""
    if inside_package(path):
        raise PrimeError(f"{what} would be written inside the installed package ({Path(path)}), whose files are "
                         "read-only templates; make the robot's own copy with `prime config init`, or name a "
                         "file elsewhere")


class _UniqueKeys(yaml.constructor.SafeConstructor):
    """YAML's safe constructor, except that a key given twice in one mapping is an error (YAML says so; PyYAML
    would silently keep the last one)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, yaml.Node] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r} (first at line {seen[key].start_mark.line + 1})",
                    key_node.start_mark)
            seen[key] = key_node
        return super().construct_mapping(node, deep=deep)


class _UniqueKeyLoader(yaml.SafeLoader, _UniqueKeys):
    pass


# libyaml's parser where PyYAML has it: a tenth of the pure-Python parser's time, the bulk of a short command's
# configuration reading. A file it refuses is read again by the pure-Python one, which words the error either way.
_FastUniqueKeyLoader = type("_FastUniqueKeyLoader", (yaml.CSafeLoader, _UniqueKeys), {}) \
    if getattr(yaml, "__with_libyaml__", False) else _UniqueKeyLoader


def config_path(path: str | Path) -> Path:
    """A configuration file's path as every message names it: absolute, so it does not depend on where the
    file is read from (the robot description resolves its includes against its own folder)."""
    return Path(path).expanduser().absolute()


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Parse a YAML configuration file whose top level is a mapping; a missing, unreadable, binary, empty or
    malformed file, a duplicate key or another top level raises ConfigError naming the file."""
    path = config_path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found", "check the path") from None
    except IsADirectoryError:
        raise ConfigError(path, "", "is a folder, not a file", "give the path of the YAML file") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(path, "", f"not UTF-8 text (byte {exc.start}); a binary file?",
                          "give the YAML file") from None
    except OSError as exc:
        raise ConfigError(path, "", f"cannot read: {exc.strerror}") from None
    try:
        try:
            data = yaml.load(text, Loader=_FastUniqueKeyLoader)  # noqa: S506 (a SafeLoader)
        except yaml.YAMLError:
            data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)
    except yaml.reader.ReaderError as exc:  # a character YAML does not allow: no mark, a position in the text
        line = text.count("\n", 0, exc.position) + 1
        column = exc.position - text.rfind("\n", 0, exc.position)
        what = "a NUL byte (0x00)" if exc.character == 0 else f"the character U+{exc.character:04X}"
        raise ConfigError(path, f"line {line}, column {column}", f"{what}, which YAML does not allow (a binary file, "
                          "or one a crash left unfinished?)", "remove it, or restore the file from a copy") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or "invalid YAML"
        if problem.startswith("duplicate key"):
            raise ConfigError(path, where, problem, "give each key once") from None
        raise ConfigError(path, where, f"malformed YAML: {problem}", "fix the syntax") from None
    if data is None:
        raise ConfigError(path, "", "the file is empty", "give the YAML document")
    if not isinstance(data, dict):
        raise ConfigError(path, "", f"expected a mapping of keys to values at the top, got a {type(data).__name__}")
    return data


def check_keys(path: str | Path, where: str, mapping: dict[str, Any], known: tuple[str, ...]) -> None:
    """Refuse a key of ``mapping`` (at ``where`` in the file) that is not one of ``known``, naming the closest
    known key: a misspelt key would otherwise leave its default silently in force."""
    for key in mapping:
        if key in known:
            continue
        close = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
        fix = f"did you mean {close[0]!r}?" if close else f"known keys here: {', '.join(known)}"
        raise ConfigError(config_path(path), f"{where}.{key}" if where else str(key), "unknown key", fix)


def output_problem(path: str | Path, *, directory: bool = False) -> str | None:
    """Why ``path`` could not be written as an output file (or, with ``directory``, filled as an output
    folder), or None. Checked before a run starts, so a run's result is never lost at its end."""
    path = Path(path).expanduser()
    if inside_package(path):
        return f"{path} is inside the installed package, whose files are read-only templates"
    if directory:
        if path.exists() and not path.is_dir():
            return f"{path} is a file, not a folder"
    elif path.is_dir():
        return f"{path} is a folder; give a file name"
    elif path.exists() and not os.access(path, os.W_OK):
        return f"{path} is read-only"
    target = (path if directory else path.parent).absolute()
    folder = target
    while not folder.exists():  # missing folders are created on write, under the first one that exists
        folder = folder.parent
    if not folder.is_dir():
        return f"{folder} is a file, so {path} cannot be created"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"cannot write in {folder}"
    return _creation_problem(folder, path.name, missing=folder != target)


def _creation_problem(folder: Path, name: str, *, missing: bool) -> str | None:
    """Why nothing can be created in ``folder`` (None: it can): tried, as the write will, with a temporary file
    named as ``atomic_write_bytes`` names it, or, where the write must first create folders under ``folder``,
    with a folder. Permission bits do not tell: /proc is writable to root, and creating a file there fails."""
    try:
        if missing:
            os.rmdir(tempfile.mkdtemp(prefix=".prime.", suffix=".tmp", dir=folder))
        else:
            fd, probe = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=folder)
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        return f"nothing can be created in {folder} ({exc.strerror or exc})"
    return None


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` atomically (see ``atomic_write_bytes``)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the complete new one, never a part.

    The data goes to a temporary file in the same folder, is flushed to disk, and is renamed over
    the target; a failure or interruption at any point leaves the previous file untouched, and a failure is a
    PrimeError that names ``path``. The file keeps the mode of the one it replaces; a new file gets the mode the
    umask gives.
    """
    path = Path(path)
    check_not_package(path)
    if path.is_dir():
        raise PrimeError(f"cannot write {path}: it is a folder; give a file name")
    try:
        _replace(path, data)
    except OSError as exc:  # named by the file the caller asked for, never by the temporary one
        raise PrimeError(f"cannot write {path}: {exc.strerror or exc}") from None


def _replace(path: Path, data: bytes) -> None:
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
