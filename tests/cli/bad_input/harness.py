"""Running one bad input in-process and judging what came of it.

A case is a command line (``{tmp}`` stands for the case's own folder) and what it must do: be refused with one
line on stderr containing given words, or be accepted. The command runs in this process (a child would cost half a
second); what would start something (a bus, a simulation, a network namespace, a web server, a benchmark) is
replaced by a tripwire that ends the command there, so a refusal that comes only after something started is caught
as such. Every outcome falls in one class: ``crash``, ``hang``, ``data loss``, ``silent accept``, ``misleading``,
``correct refusal``, ``correct acceptance``."""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import signal
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from humanoid_prime.cli import main
from humanoid_prime.files import package_root

HANG_S = 20.0  # far above any refusal on a loaded machine; a command that gets this far is waiting on something
CLASSES = ("data loss", "crash", "silent accept", "misleading", "hang", "correct refusal", "correct acceptance")
TOTALS: Counter[str] = Counter()  # every case run in this session, by class (reported at the end)


class Started(BaseException):
    """A tripwire fired: the command went on to start something (not an Exception, so nothing swallows it)."""


class Hung(BaseException):
    """The command was still running after HANG_S."""


# What starts something, by module and name; each is replaced for the duration of a case.
TRIPWIRES = (
    ("humanoid_prime.runtime.session", "open_session"),
    ("humanoid_prime.virtual.harness", "enter_private_netns"),
    ("humanoid_prime.virtual.harness", "attach_virtual_prime"),
    ("humanoid_prime.sim.demo", "build_simulation"),
    ("humanoid_prime.cli.sim", "build_simulation"),
    ("humanoid_prime.cli.sim", "build_hil_simulation"),
    ("humanoid_prime.drivers.sito.bus", "open_bus"),
    ("humanoid_prime.cli.can", "open_bus"),
    ("humanoid_prime.drivers.ethercat.sdo", "open_sdo"),
    ("humanoid_prime.cli.ec", "open_sdo"),
    ("humanoid_prime.view.page", "PrimeView"),
    ("humanoid_prime.cli.bench", "Working"),
    ("humanoid_prime.cli.emulate", "EmulatedRing"),
    ("humanoid_prime.cli.emulate", "reexec_in_user_netns"),
    ("humanoid_prime.virtual.ring.__main__", "main"),
    ("humanoid_prime.dds.remote", "RemoteClient"),
    ("humanoid_prime.view.feeds", "DdsSource"),
    ("humanoid_prime.dds.bridge", "bridge_manager"),
)


@dataclass
class Outcome:
    code: int | None
    out: str
    err: str
    started: str | None = None  # the tripwire that fired
    hung: bool = False
    exception: BaseException | None = None  # anything that escaped main()
    changed: list[str] = field(default_factory=list)  # pre-existing files changed or removed

    @property
    def lines(self) -> list[str]:
        return [line for line in self.err.splitlines() if line.strip()]


_DESCRIPTIONS: dict[tuple, Any] = {}


def _remembered_description(original: Any) -> Any:
    """``load_description`` remembered per hardware file content: the description of the same bytes is the
    same, and rendering it (xacro) is most of what a case costs."""
    def load(hardware: Any, **options: Any) -> Any:
        key = (Path(hardware.path).read_bytes(), tuple(sorted(options.items())))
        if key not in _DESCRIPTIONS:
            _DESCRIPTIONS[key] = original(hardware, **options)
        return _DESCRIPTIONS[key]
    return load


def _tripwire(name: str) -> Any:
    def fire(*args: Any, **kwargs: Any) -> Any:
        raise Started(name)
    return fire


def _hang(signum: int, frame: Any) -> None:
    raise Hung


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (the case's) by content, and the installed package's files by size and mtime."""
    state = {}
    for path in sorted(folder.rglob("*")):
        if path.is_file() and not path.is_socket():
            state[str(path)] = hashlib.sha256(path.read_bytes()).hexdigest()
    root = package_root()
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        for name in filenames:
            st = os.stat(os.path.join(dirpath, name))
            state[os.path.join(dirpath, name)] = f"{st.st_size}:{st.st_mtime_ns}"
    return state


def run_prime(argv: list[str], folder: Path, monkeypatch: Any) -> Outcome:
    """``prime argv`` in-process with its stdout and stderr captured, tripwires set and a hang timer running."""
    import importlib

    for module, name in TRIPWIRES:
        mod = importlib.import_module(module)
        original = getattr(mod, name, None)
        if original is None:
            continue
        wire = _tripwire(f"{module}.{name}")
        monkeypatch.setattr(mod, name, wire)
        for other in list(sys.modules.values()):  # where a command imported it by name
            if getattr(other, "__name__", "").startswith("humanoid_prime.cli") and \
                    getattr(other, name, None) is original:
                monkeypatch.setattr(other, name, wire)
    import humanoid_prime.config.robot as robot_module
    from humanoid_prime.config.description import load_description

    monkeypatch.setattr(robot_module, "load_description", _remembered_description(load_description))
    monkeypatch.chdir(folder)
    before = snapshot(folder)
    out, err = io.StringIO(), io.StringIO()
    outcome = Outcome(None, "", "")
    previous = signal.signal(signal.SIGALRM, _hang)
    signal.setitimer(signal.ITIMER_REAL, HANG_S)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
                contextlib.ExitStack() as stack:
            stack.enter_context(_stdin_closed(monkeypatch))
            try:
                outcome.code = main(list(argv))
            except SystemExit as exc:  # argparse
                outcome.code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            except Started as exc:
                outcome.started = str(exc)
            except Hung:
                outcome.hung = True
            except BaseException as exc:  # noqa: BLE001 -- judged below
                outcome.exception = exc
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    outcome.out, outcome.err = out.getvalue(), err.getvalue()
    after = snapshot(folder)
    outcome.changed = sorted(path for path, digest in before.items() if after.get(path) != digest)
    return outcome


@contextlib.contextmanager
def _stdin_closed(monkeypatch: Any) -> Any:
    monkeypatch.setattr(sys, "stdin", io.StringIO(""))
    yield


def classify(outcome: Outcome, expect: str, needles: tuple[str, ...] = ()) -> tuple[str, str]:
    """The class of ``outcome`` for a case that should be ``expect`` ("refuse" or "accept"), and why."""
    if outcome.changed:
        return "data loss", f"changed: {', '.join(outcome.changed)}"
    if outcome.hung:
        return "hang", f"still running after {HANG_S:g} s"
    text = outcome.err
    if outcome.exception is not None or "Traceback" in text or outcome.code == 70 or "internal error" in text:
        return "crash", repr(outcome.exception) if outcome.exception is not None else text
    if expect == "accept":
        if outcome.code in (0, None) and (outcome.started or outcome.code == 0):
            return "correct acceptance", outcome.started or "exit 0"
        return "misleading", f"refused what it should accept (exit {outcome.code}): {text.strip()}"
    if outcome.started is not None:
        return "silent accept", f"started ({outcome.started}) before refusing; stderr: {text.strip()!r}"
    if outcome.code == 0:
        return "silent accept", f"exit 0; stdout: {outcome.out.strip()[:300]!r}"
    if len(outcome.lines) != 1 or not text.endswith("\n"):
        return "misleading", f"{len(outcome.lines)} lines on stderr: {text!r}"
    missing = [n for n in needles if n not in outcome.lines[0]]
    if missing:
        return "misleading", f"the line does not say {missing}: {outcome.lines[0]!r}"
    return "correct refusal", outcome.lines[0]


def check(argv: list[str], folder: Path, monkeypatch: Any, expect: str = "refuse",
          needles: tuple[str, ...] = ()) -> Outcome:
    """Run a case and fail the test unless it is a correct refusal (or acceptance); the class is counted."""
    values = {"tmp": str(folder)}
    argv = [a.format(**values) for a in argv]
    needles = tuple(n.format(**values) for n in needles)
    outcome = run_prime(argv, folder, monkeypatch)
    kind, why = classify(outcome, expect, needles)
    TOTALS[kind] += 1
    assert kind == ("correct refusal" if expect == "refuse" else "correct acceptance"), \
        f"{kind}: prime {' '.join(argv)}: {why}"
    return outcome
