"""``--web``: the live 3D view of the run in a browser (``view/page.py``); its mode buttons take the run's mode
request path."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Callable
from typing import TYPE_CHECKING

from humanoid_prime.cli._common import add_web_option, check_web
from humanoid_prime.cli.addons import Run

if TYPE_CHECKING:
    from humanoid_prime.calibration.tracker import SweepTracker
    from humanoid_prime.runtime.session import Session


def options(parser: argparse.ArgumentParser) -> None:
    add_web_option(parser)


def check(args: argparse.Namespace) -> bool:
    if hasattr(args, "emulate"):
        check_web(args)
    return args.web is not None


def attach(run: Run, args: argparse.Namespace, stack: contextlib.ExitStack) -> None:
    from humanoid_prime.view.feeds import manager_source
    from humanoid_prime.view.page import PrimeView

    source = run.state
    if source is None:
        source, detach = manager_source(run.manager)
        stack.callback(detach)
    view = PrimeView(run.manager.robot, port=args.web, request_mode=run.request_mode or run.manager.request_mode,
                     source=source, title=run.title)
    stack.callback(view.close)
    run.report(f"view: {view.url}")


class CalibrationView:
    """``prime calibrate --web``: one page for the whole run, showing each phase's joints and the ranges swept so
    far (a calibration runs a session per phase, where the add-on above follows one)."""

    def __init__(self, port: int | None, hardware_file: str | None, stack: contextlib.ExitStack) -> None:
        self.view = None
        self.phase: tuple[Callable[[], dict[str, object]], SweepTracker] | None = None  # its state, its sweeps
        self.swept: dict[str, tuple[float, float]] = {}  # the phases before this one
        if port is None:
            return
        from humanoid_prime.config.robot import load_robot
        from humanoid_prime.view.page import PrimeView

        self.robot = load_robot(hardware_file)
        self.view = PrimeView(self.robot, port=port, source=self._state, sweeps=True, title="Prime calibration")
        stack.callback(self.view.close)
        print(f"view: {self.view.url}", flush=True)

    def attach(self, session: Session, tracker: SweepTracker, stack: contextlib.ExitStack) -> None:
        if self.view is None:
            return
        from humanoid_prime.view.feeds import manager_source

        state, detach_state = manager_source(session.manager)
        self.phase = (state, tracker)

        def detach() -> None:
            self.swept.update(tracker.sweeps())
            detach_state()
            self.phase = None

        stack.callback(detach)

    def _state(self) -> dict[str, object]:
        phase = self.phase
        if phase is None:
            raise ConnectionError("between phases")
        state, tracker = phase
        swept = {**self.swept, **tracker.sweeps()}
        nothing = (float("inf"), float("-inf"))
        return {**state(), "sweeps": [swept.get(name, nothing) for name in self.robot.names]}
