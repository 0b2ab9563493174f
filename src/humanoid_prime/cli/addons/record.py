"""``--record FILE.mcap``: every topic of the run to an MCAP file (``record/mcap.py``); its figures in the
summary under ``record``."""

from __future__ import annotations

import argparse
import contextlib

from humanoid_prime.cli._common import add_record_option
from humanoid_prime.cli.addons import Run, Summary


def options(parser: argparse.ArgumentParser) -> None:
    add_record_option(parser)


def check(args: argparse.Namespace) -> bool:
    return args.record is not None


def attach(run: Run, args: argparse.Namespace, stack: contextlib.ExitStack) -> Summary:
    from humanoid_prime.record.mcap import Recorder

    recorder = Recorder(args.record, run.manager, epoch_offset=run.epoch_offset, wait=run.wait)
    stack.callback(recorder.close)  # the file is finished before the run's teardown
    return recorder.summary
