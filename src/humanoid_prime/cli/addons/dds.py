"""``--dds``: the run is node ``prime`` on the ROS 2 graph (``dds/bridge.py``); its figures in the summary
under ``dds``."""

from __future__ import annotations

import argparse
import contextlib

from humanoid_prime.cli._common import add_dds_options, dds_options
from humanoid_prime.cli.addons import Run, Summary


def options(parser: argparse.ArgumentParser) -> None:
    add_dds_options(parser, node=True)


def check(args: argparse.Namespace) -> bool:
    return dds_options(args) is not None


def attach(run: Run, args: argparse.Namespace, stack: contextlib.ExitStack) -> Summary:
    from humanoid_prime.dds.bridge import bridge_manager

    dds = dds_options(args)
    network = run.host_graph() if run.host_graph is not None else contextlib.nullcontext(True)
    with network as on_host:
        bridge = bridge_manager(run.manager, domain=dds.domain, namespace=dds.namespace, control=dds.control,
                                request_mode=run.request_mode, epoch_offset=run.epoch_offset,
                                sim_clock=run.sim_clock, settings=dds.discovery)
    stack.callback(bridge.close)  # off the graph before the run's teardown
    where = "" if on_host else (" (inside the emulation's private network namespace: only processes in it can "
                                "join; run as root to put the node on this machine's graph)")
    run.report(f"DDS: {dds.describe()}{where}")
    return bridge.summary
