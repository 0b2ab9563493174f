"""Every command block of the README and the manual (docs/*.md) runs as written, in the order written, by a new
user: a fresh HOME with nothing configured, `prime` on the PATH as `. .venv/bin/activate` puts it there, the page's
own folder for the files it names. So the documentation cannot drift from the command line; and every link between
the pages (a page, an image, a heading's anchor) resolves.

A ```sh block is run line by line; each line must exit 0. A comment just before a block says how to run it where
running it as written would need the real robot, or would not end:

- ``<!-- test: skip, REASON -->``: not run (the reason says why: it is the test suite itself, say);
- ``<!-- test: instead: COMMAND -->``: run COMMAND in place of the block (a real robot's command on the virtual
  one, ``--emulate``, or an interface name); it is held to the same exit status;
- ``<!-- test: background -->``: each line starts a process that runs on (a simulation, a bring-up); the next
  blocks run beside it, and it is stopped (Ctrl-C) when the page ends, and must then exit 0;
- ``<!-- test: exit N -->``: each line must exit N (an example of a refusal).
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from doubles.domains import domain_ids
from humanoid_prime.errors import PrimeError
from humanoid_prime.runtime.socket import request

REPOSITORY = Path(__file__).parents[1]
PAGES = [REPOSITORY / "README.md", *sorted((REPOSITORY / "docs").glob("*.md"))]
BLOCK = re.compile(r"(?:<!--\s*test:\s*(?P<directive>.*?)\s*-->\s*\n)?```sh\n(?P<body>.*?)```", re.S)
DOMAINS = domain_ids()  # this worker's own ROS 2 domains
STARTUP_S = 120.0  # a background process answers on its control socket within this (a loaded machine, MuJoCo)


@dataclass
class Block:
    page: Path
    line: int
    directive: str
    commands: list[str]


def blocks(page: Path) -> list[Block]:
    """The page's ```sh blocks, each with the directive before it and its command lines (comments dropped)."""
    text = page.read_text()
    found = []
    for match in BLOCK.finditer(text):
        commands = []
        for raw in match.group("body").splitlines():
            line = raw.split(" #")[0].strip() if not raw.lstrip().startswith("#") else ""
            if line:
                commands.append(line)
        found.append(Block(page, text.count("\n", 0, match.start("body")) + 1, match.group("directive") or "",
                           commands))
    return found


def test_every_page_has_examples_and_every_directive_is_known():
    for page in PAGES:
        found = blocks(page)
        assert found, f"{page.name} has no ```sh example"
        for block in found:
            assert block.commands, f"{page.name}:{block.line}: an empty block"
            kind = _kind(block.directive)
            assert kind in ("", "skip", "instead", "background", "exit"), f"{page.name}:{block.line}: {kind!r}"
            if kind == "skip":
                assert "," in block.directive, f"{page.name}:{block.line}: a skip says why"


LINK = re.compile(r"\]\((?!https?://)(?P<target>[^)#\s]*)(?:#(?P<anchor>[^)\s]+))?\)")


def _anchors(page: Path) -> set[str]:
    """The anchors a page's headings get (GitHub's rule: lower case, punctuation dropped, spaces to hyphens)."""
    headings = re.findall(r"^#+\s+(.*?)\s*$", page.read_text(), re.M)
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in headings}


def test_every_link_between_pages_resolves():
    for page in PAGES:
        for match in LINK.finditer(page.read_text()):
            target = (page.parent / match["target"]).resolve() if match["target"] else page
            where = f"{page.name}: ({match['target']}#{match['anchor'] or ''})"
            assert target.is_file(), f"{where}: no such file"
            if match["anchor"]:
                assert match["anchor"] in _anchors(target), f"{where}: no such heading"


def _kind(directive: str) -> str:
    """The directive's first word: skip, instead, background or exit ("" for none)."""
    words = re.split(r"[\s:,]+", directive.strip(), maxsplit=1)
    return words[0]


@pytest.fixture
def user(tmp_path, monkeypatch) -> dict[str, str]:
    """A new user's shell: a fresh HOME, no configuration, `prime` on the PATH, one control socket, and a ROS 2
    domain of its own on this machine (as a quiet network would be)."""
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PRIME_", "XDG_CONFIG"))}
    env.update(HOME=str(home), PATH=f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}",
               PRIME_CONTROL_SOCKET=str(tmp_path / "sock" / "control.sock"),
               ROS_DOMAIN_ID=str(next(DOMAINS)), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    return env


def _socket(command: str, env: dict[str, str], work: Path) -> str:
    """The control socket a command answers on: its --socket, else the user's."""
    words = shlex.split(command)
    if "--socket" in words:
        return str(work / words[words.index("--socket") + 1])
    return env["PRIME_CONTROL_SOCKET"]


def _as_in_a_terminal() -> None:
    """Ctrl-C as a terminal delivers it: a suite started as a background job inherits SIGINT ignored."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _serves_a_page(command: str) -> bool:
    """prime view and prime replay are ready when they print their page's address, not on a control socket."""
    words = shlex.split(command)
    return len(words) > 1 and words[1] in ("view", "replay")


def _wait_until_ready(command: str, env: dict[str, str], work: Path, process: subprocess.Popen, output: Path,
                      what: str) -> None:
    deadline = time.monotonic() + STARTUP_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"{what} ended at once with {process.returncode}: {output.read_text()[-2000:]}")
        if _serves_a_page(command):
            if "http://" in output.read_text():
                return
        else:
            try:
                if request(_socket(command, env, work), {"op": "ping"}, timeout=0.5)["ready"]:
                    return
            except PrimeError:
                pass
        time.sleep(0.2)
    raise AssertionError(f"{what} was not ready within {STARTUP_S:g} s: {output.read_text()[-2000:]}")


def _on_the_virtual_robot(page: Path) -> bool:
    """The page runs something on the emulated robot (a network namespace, on the wall clock): a real-time test."""
    return any(re.search(r"--emulate\b|\bemulate ec\b", command)
               for block in blocks(page) if _kind(block.directive) != "skip"
               for command in ([block.directive] if _kind(block.directive) == "instead" else block.commands))


@pytest.mark.parametrize("page", [pytest.param(p, marks=pytest.mark.netns) if _on_the_virtual_robot(p) else p
                                  for p in PAGES], ids=[p.name for p in PAGES])
def test_every_example_of_the_page_runs_as_written(page, user, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    running: list[tuple[str, subprocess.Popen, Path]] = []
    try:
        for block in blocks(page):
            kind = _kind(block.directive)
            if kind == "skip":
                continue
            rest = block.directive.strip()[len(kind):].lstrip(" :,")
            commands = [rest] if kind == "instead" else block.commands
            expected = int(rest) if kind == "exit" else 0
            for command in commands:
                where = f"{page.name}:{block.line}: {command}"
                if kind == "background":  # `exec`: Ctrl-C reaches the command itself, as in a terminal
                    output = tmp_path / f"background-{len(running)}.log"
                    with output.open("w") as sink:
                        process = subprocess.Popen(["sh", "-c", f"exec {command}"], cwd=work, env=user, text=True,
                                                   stdout=sink, stderr=subprocess.STDOUT, preexec_fn=_as_in_a_terminal)
                    running.append((where, process, output))
                    _wait_until_ready(command, user, work, process, output, where)
                    continue
                done = subprocess.run(command, shell=True, cwd=work, env=user, capture_output=True, text=True,
                                      timeout=600, stdin=subprocess.DEVNULL)
                assert done.returncode == expected, f"{where} exited {done.returncode}:\n{done.stderr[-2000:]}"
    finally:
        for where, process, _ in running:
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
                raise AssertionError(f"{where} did not stop on Ctrl-C") from None
    for where, process, output in running:
        assert process.returncode in (0, 130), f"{where} ended with {process.returncode}: {output.read_text()[-2000:]}"
