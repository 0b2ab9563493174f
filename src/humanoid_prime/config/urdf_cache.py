"""The URDF xacro expands to, kept in the user's cache folder: expanding takes about 0.3 s, the whole start-up
budget of a command such as `prime info`, and gives the same text for the same files.

An entry lives in ``$XDG_CACHE_HOME/prime/urdf/`` (default ``~/.cache/prime``, never inside the package), named by
the hash of xacro's own source, the top file's path and content, and the arguments (with the content of the files
they name). It records every file the expansion read (includes, the YAML it loaded) with its hash, and is used
only while each of them still holds that content; anything unreadable is a miss. A folder that cannot be written
costs the time, nothing else."""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import json
import os
from collections.abc import Callable, Mapping
from pathlib import Path

from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_text

FORMAT = 1  # bump when an entry's layout changes
KEPT_ENTRIES = 32  # a few robots' descriptions, simulated and real, at a few rates each


def cache_folder() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "prime" / "urdf"


def expand_cached(source: Path, mappings: Mapping[str, str], expand: Callable[[], str]) -> str:
    """``expand()`` (xacro on ``source`` with ``mappings``), or what it gave before for the same files."""
    try:
        entry_path = cache_folder() / f"{_key(source, mappings)}.json"
    except OSError:  # a file missing: xacro says which
        return expand()
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError, AttributeError):
        entry = json.loads(entry_path.read_text(encoding="utf-8"))
        if entry["format"] == FORMAT and all(_digest(Path(p)) == h for p, h in entry["reads"].items()):
            return str(entry["urdf"])
    import xacro

    first = len(xacro.all_includes)  # xacro lists every file it reads in this module-wide list
    urdf = expand()
    reads = {str(p): _digest(Path(p)) for p in sorted(set(xacro.all_includes[first:]) | {str(source)})}
    with contextlib.suppress(OSError, PrimeError):
        atomic_write_text(entry_path, json.dumps({"format": FORMAT, "reads": reads, "urdf": urdf}))
        _prune(entry_path.parent)
    return urdf


def _prune(folder: Path) -> None:
    """Keep the ``KEPT_ENTRIES`` newest entries: descriptions edited, or copied and gone, leave entries nobody
    reads again."""
    entries = sorted(folder.glob("*.json"), key=lambda path: path.stat().st_mtime, reverse=True)
    for stale in entries[KEPT_ENTRIES:]:
        stale.unlink(missing_ok=True)


def _key(source: Path, mappings: Mapping[str, str]) -> str:
    spec = importlib.util.find_spec("xacro")
    parts: list[str] = [str(FORMAT), _digest(Path(spec.origin)) if spec and spec.origin else "no xacro",
                        str(source), _digest(source)]
    for name, value in sorted(mappings.items()):
        parts += [name, value, _digest(Path(value)) if value and Path(value).is_file() else ""]
    return hashlib.sha256("\0".join(parts).encode()).hexdigest()


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()

