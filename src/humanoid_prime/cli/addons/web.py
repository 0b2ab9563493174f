"""``--web``: the live 3D view of the run in a browser (``view/page.py``); its mode buttons take the run's mode
request path."""

from __future__ import annotations

import argparse
import contextlib

from humanoid_prime.cli._common import add_web_option, check_web
from humanoid_prime.cli.addons import Run


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
