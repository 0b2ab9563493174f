"""``--dds``: the run is node ``prime`` on the ROS 2 graph, as an rclpy node where rclpy can be imported
(``dds/rclpy_node.py``) or as one bare Cyclone DDS participant (``dds/bridge.py``), ``--ros-backend`` to choose;
its figures in the summary under ``dds``."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
from typing import TYPE_CHECKING

from humanoid_prime.cli._common import add_dds_options, dds_options
from humanoid_prime.cli.addons import Run, Summary
from humanoid_prime.control.flags import Level
from humanoid_prime.errors import PrimeError

if TYPE_CHECKING:  # the options are added without importing the node
    from humanoid_prime.dds.controllers import Switch
    from humanoid_prime.modes import Mode


def options(parser: argparse.ArgumentParser) -> None:
    add_dds_options(parser, node=True)


def check(args: argparse.Namespace) -> bool:
    return dds_options(args) is not None


def attach(run: Run, args: argparse.Namespace, stack: contextlib.ExitStack) -> Summary:
    dds = dds_options(args)
    assert dds is not None  # check() said the user asked for it

    def log(line: str, level: Level | None) -> None:
        run.report(line if level is None else f"{level.name.lower()}: {line}")

    backend = dds.backend
    if backend == "rclpy":
        try:
            from humanoid_prime.dds.rclpy_node import rclpy_bridge
        except ImportError as exc:  # found but broken (a ROS 2 install half sourced, a library missing)
            if dds.backend_asked:
                raise PrimeError(f"--ros-backend rclpy: rclpy does not import here ({exc}); source the ROS 2 install "
                                 "completely, or run with --ros-backend dds") from None
            run.report(f"rclpy does not import here ({exc}): the bare DDS node instead")
            backend = "dds"
    network = run.host_graph() if run.host_graph is not None else contextlib.nullcontext(True)
    with network as on_host:
        if backend == "rclpy":
            bridge = rclpy_bridge(run.manager, domain=dds.domain, namespace=dds.namespace, control=dds.control,
                                  request_mode=run.request_mode, switch=_switch(run), epoch_offset=run.epoch_offset,
                                  sim_clock=run.sim_clock, report=log)
            started = bridge.started()
        else:
            from humanoid_prime.dds.bridge import bridge_manager

            bridge = bridge_manager(run.manager, domain=dds.domain, namespace=dds.namespace, control=dds.control,
                                    request_mode=run.request_mode, epoch_offset=run.epoch_offset,
                                    sim_clock=run.sim_clock, settings=dds.discovery, report=log)
            started = f"DDS: {dataclasses.replace(dds, backend=backend).describe()}"
    stack.callback(bridge.close)  # off the graph before the run's teardown
    where = "" if on_host else (" (inside the emulation's private network namespace: only processes in it can "
                                "join; run as root to put the node on this machine's graph)")
    run.report(f"{started}{where}")
    return bridge.summary


def _switch(run: Run) -> Switch:
    """The run's mode switch, followed to its outcome as `prime switch` follows it, for the node's services."""
    from humanoid_prime.dds.controllers import SwitchResult
    from humanoid_prime.runtime.switching import describe, mode_switcher

    switcher = run.switch or mode_switcher(run.manager)

    def switch(mode: Mode, wait_s: float) -> SwitchResult:
        answer = switcher(mode, wait_s)
        return SwitchResult(answer["outcome"], answer.get("active") or "", describe(answer))

    return switch
