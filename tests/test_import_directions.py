"""The package's rooms import one way: cli -> runtime -> record -> dds -> calibration -> drivers -> control -> config ->
foundation (errors, files, modes, interrupts), with the simulation, the virtual Prime, the benchmarks and the view
beside the CLI.
Production code never imports what pretends to be hardware (virtual/)."""

from __future__ import annotations

import ast
from pathlib import Path

import humanoid_prime

PACKAGE = Path(humanoid_prime.__file__).parent
FOUNDATION = {"errors", "files", "modes", "interrupts", "__init__"}
LAYERS = ("foundation", "config", "control", "drivers", "calibration", "dds", "record", "runtime")
APPS = {  # rooms above the layers, and which of their peers each may import
    "sim": set(),
    "virtual": {"sim"},
    "bench": {"sim", "virtual", "doctor"},
    "view": set(),
    "doctor": set(),
    "cli": {"sim", "virtual", "bench", "view", "doctor"},
    "__main__": {"cli"},
}


def room(module: str) -> str:
    """The room of a module path inside the package ('humanoid_prime.drivers.sito.system' -> 'drivers')."""
    first = module.split(".")[1] if "." in module else "__init__"
    return "foundation" if first in FOUNDATION else first


def allowed(source: str) -> set[str]:
    if source in LAYERS:
        return set(LAYERS[: LAYERS.index(source) + 1])
    return {*LAYERS, source, *APPS[source]}


def imports(path: Path) -> list[tuple[int, str]]:
    """Every humanoid_prime module ``path`` imports, with its line, wherever the import statement sits."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("humanoid_prime"):
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names if alias.name.startswith("humanoid_prime")]
    return found


def modules() -> list[tuple[str, Path]]:
    result = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE.parent).with_suffix("")
        result.append((".".join(relative.parts), path))
    return result


def test_every_module_belongs_to_a_known_room():
    rooms = {room(name) for name, _ in modules()}
    assert rooms <= {*LAYERS, *APPS}, rooms - {*LAYERS, *APPS}


def test_imports_run_one_way_between_rooms():
    wrong = []
    for name, path in modules():
        source = room(name)
        for line, target in imports(path):
            if target == "humanoid_prime":
                continue  # the package itself: its version
            if room(target) not in allowed(source):
                wrong.append(f"{path.relative_to(PACKAGE)}:{line} ({source}) imports {target} ({room(target)})")
    assert not wrong, "imports against the direction of the rooms:\n" + "\n".join(wrong)


def test_only_the_simulation_benchmarks_and_cli_reach_the_virtual_prime():
    importers = {room(name) for name, path in modules() for _, target in imports(path)
                 if room(target) == "virtual" and room(name) != "virtual"}
    assert importers <= {"bench", "cli"}, importers


def test_the_direction_check_sees_a_wrong_import(tmp_path):
    """The checker itself: a driver importing the runtime is caught."""
    bad = tmp_path / "bad.py"
    bad.write_text("from humanoid_prime.runtime.session import Session\n")
    assert [room(target) for _, target in imports(bad)] == ["runtime"]
    assert "runtime" not in allowed("drivers")
