"""Bad configuration files, generated from the bundled templates: every key of the hardware, calibration and
controllers files removed, given a value of the wrong type, and given a value out of range; and each file
corrupted whole (empty, binary, truncated, a folder, missing). ``prime bringup`` reads all three and checks them
together before it opens a bus: each is refused with one line naming the file and the key."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from cli.bad_input.cases import fill
from cli.bad_input.harness import check
from humanoid_prime.files import bundled

FILES = {"hardware": "prime_hardware.yaml", "calibration": "prime_calibration.yaml",
         "controllers": "prime_controllers.yaml"}


def _leaves(data, path=()):
    if isinstance(data, dict):
        for key, value in data.items():
            yield from _leaves(value, (*path, key))
    elif isinstance(data, list):
        for index, value in enumerate(data):
            yield from _leaves(value, (*path, index))
    else:
        yield path, data


def _wrong_type(value):
    if isinstance(value, bool):
        return "maybe"
    if isinstance(value, (int, float)):
        return "abc"
    return [1, 2]


def _out_of_range(value):
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return -1
    if isinstance(value, float):
        return 1e308
    return ""  # every word the files hold names something: none may be empty


# (file, key path, mutation) accepted by design, with the reason.
ACCEPTED: dict[tuple[str, str, str], str] = {}


def _cases():
    cases = []
    for which, file in FILES.items():
        data = yaml.safe_load(bundled(file).read_text())
        for path, value in _leaves(data):
            dotted = ".".join(str(p) for p in path)
            for mutation, new in (("missing", ...), ("wrong type", _wrong_type(value)),
                                  ("out of range", _out_of_range(value))):
                if new is None:
                    continue
                expect = "accept" if (which, dotted, mutation) in ACCEPTED else "refuse"
                cases.append(pytest.param(which, path, new, expect, id=f"{which} {dotted} {mutation}"))
    return cases


def _write(folder: Path, which: str, path: tuple, new) -> Path:
    data = yaml.safe_load(bundled(FILES[which]).read_text())
    edited = copy.deepcopy(data)
    parent = edited
    for key in path[:-1]:
        parent = parent[key]
    if new is ...:
        del parent[path[-1]]
    else:
        parent[path[-1]] = new
    target = folder / f"my_{which}.yaml"
    target.write_text(yaml.safe_dump(edited, sort_keys=False))
    return target


@pytest.fixture
def folder(tmp_path):
    fill(tmp_path)
    return tmp_path


@pytest.mark.parametrize("which, path, new, expect", _cases())
def test_a_key_missing_of_the_wrong_type_or_out_of_range_is_one_line_naming_file_and_key(
        folder, monkeypatch, which, path, new, expect):
    bad = _write(folder, which, path, new)
    key = str(path[-1]) if not isinstance(path[-1], int) else str(path[-2])
    check(["bringup", f"--{which}", str(bad)], folder, monkeypatch, expect=expect, needles=(str(bad), key))
