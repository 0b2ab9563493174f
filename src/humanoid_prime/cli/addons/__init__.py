"""Add-ons: what a run can carry beside the loop (a recording, the ROS 2 node, the live view), attached in one
place. An add-on is a module (or any object) with three functions:

- ``options(parser)`` adds the command-line options it owns;
- ``check(args) -> bool`` checks them before anything opens (a PrimeError says what is wrong) and says whether
  the user asked for the add-on;
- ``attach(run, args, stack) -> summary | None`` attaches it to the running ``Run``, registers its teardown on
  ``stack`` (closed before the run's own teardown) and returns what gives its figures for the summary (read
  after ``stack`` has closed), or None when it has none. An add-on that can go on with the run's next
  controller manager (a calibration runs one session per bus) adds itself to ``run.followers``.

``ADDONS`` names them, python-can's way (``can/interfaces/__init__.py``): a module path (imported when used)
or the add-on itself. A new add-on is its module and one line here, or in a user's launcher
(``ADDONS["mine"] = "my_package.prime_addon"`` before ``humanoid_prime.cli.main()``). A command chooses its
add-ons when it adds their options; by default every one registered.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Protocol

from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.switching import SwitchAnswer

Summary = Callable[[], dict[str, Any]]


@dataclass
class Run:
    """What an add-on attaches to: the run's controller manager, and how this run stamps, speaks and switches."""

    manager: ControllerManager
    report: Callable[[str], None]  # a startup line ("view: URL"), where the command prints them
    request_mode: Callable[[str], Any] | None = None  # an operator's mode request (None: the manager's own)
    switch: Callable[[Mode, float], SwitchAnswer] | None = None  # a switch followed to its outcome (None: the
    # manager's own, as runtime.switching.mode_switcher makes it)
    epoch_offset: float = 0.0  # added to the loop's monotonic stamps for the system clock, as on the robot
    sim_clock: bool = False  # stamps are simulated time, published on /clock for ROS 2's use_sim_time
    wait: bool = False  # no real-time deadline (--fast): a writer makes the loop wait rather than drop a tick
    title: str = "Prime"
    state: Callable[[], dict[str, Any]] | None = None  # the run's state source if it keeps one (None: its own)
    host_graph: Callable[[], contextlib.AbstractContextManager[bool]] | None = None  # enter to be on this
    # machine's ROS 2 graph (an emulated run lives in a private network namespace); yields whether it is
    followers: list[Callable[[ControllerManager, contextlib.ExitStack], None]] = field(default_factory=list)

    def follow(self, manager: ControllerManager, stack: contextlib.ExitStack) -> None:
        """The run goes on with ``manager`` (also the first one), whose teardown is ``stack``: every add-on that
        follows moves to it, and lets go of it on ``stack`` before it shuts down."""
        self.manager = manager
        for follow in self.followers:
            follow(manager, stack)


class Addon(Protocol):
    def options(self, parser: argparse.ArgumentParser) -> None: ...

    def check(self, args: argparse.Namespace) -> bool: ...

    def attach(self, run: Run, args: argparse.Namespace, stack: contextlib.ExitStack) -> Summary | None: ...


ADDONS: dict[str, str | Addon | ModuleType] = {
    "record": "humanoid_prime.cli.addons.record",
    "dds": "humanoid_prime.cli.addons.dds",
    "web": "humanoid_prime.cli.addons.web",
}


def addon(name: str) -> Addon:
    """The add-on registered as ``name``."""
    entry = ADDONS[name]
    return importlib.import_module(entry) if isinstance(entry, str) else entry  # type: ignore[return-value]


def add_addon_options(parser: argparse.ArgumentParser, names: Iterable[str] | None = None) -> None:
    """The options of the add-ons ``names`` (default: every one registered), which the command then carries."""
    chosen = tuple(ADDONS if names is None else names)
    for name in chosen:
        addon(name).options(parser)
    parser.set_defaults(addons=chosen)


def check_addons(args: argparse.Namespace, names: Iterable[str] | None = None) -> list[str]:
    """Check the options of the add-ons ``names`` (default: the command's) before anything opens; the names of
    those the user asked for."""
    return [name for name in (args.addons if names is None else names) if addon(name).check(args)]


class Addons:
    """The add-ons attached to a run: ``attach`` attaches those the user asked for, ``summaries`` gives their
    figures by name once the stack they were attached on has closed (those attached before a failure too)."""

    def __init__(self) -> None:
        self.providers: dict[str, Summary] = {}

    def attach(self, run: Run, args: argparse.Namespace, stack: contextlib.ExitStack,
               names: Iterable[str] | None = None) -> None:
        """Attach every add-on of the command (or of ``names``) that the user asked for, in the order given."""
        for name in check_addons(args, names):
            provider = addon(name).attach(run, args, stack)
            if provider is not None:
                self.providers[name] = provider

    def summaries(self) -> dict[str, dict[str, Any]]:
        return {name: provider() for name, provider in self.providers.items()}
