"""``--record FILE.mcap``: every topic of the run to an MCAP file (``record/mcap.py``); its figures in the
summary under ``record``."""

from __future__ import annotations

import argparse
import contextlib

from humanoid_prime.cli._common import add_record_option
from humanoid_prime.cli.addons import Run, Summary
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.errors import PrimeError


def options(parser: argparse.ArgumentParser) -> None:
    add_record_option(parser)


def check(args: argparse.Namespace) -> bool:
    if args.topics is not None and args.record is None:
        raise PrimeError("--topics needs --record")
    return args.record is not None


def attach(run: Run, args: argparse.Namespace, stack: contextlib.ExitStack) -> Summary:
    from humanoid_prime.record.mcap import Recorder

    recorder = Recorder(args.record, run.manager, epoch_offset=run.epoch_offset, wait=run.wait,
                        sim_clock=run.sim_clock, topics=args.topics)
    stack.callback(recorder.close)  # the file is finished before the run's teardown
    recording = [run.manager]

    def follow(manager: ControllerManager, session: contextlib.ExitStack) -> None:
        """One file for the whole run: each next manager's ticks go on in it."""
        if manager is not recording[0]:
            recorder.attach(manager)
            recording[0] = manager
        session.callback(recorder.detach)  # before that manager shuts down

    run.followers.append(follow)
    return recorder.summary
