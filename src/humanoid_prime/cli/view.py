"""``prime view``: the live 3D view of a running Prime in the browser; ``prime replay``: a recording played
into the same view."""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import (
    DEFAULT_WEB_PORT,
    add_config_options,
    add_dds_options,
    add_socket_option,
    dds_domain,
    real,
    whole,
)
from humanoid_prime.config.robot import load_robot
from humanoid_prime.runtime.signals import stop_on_signals

if TYPE_CHECKING:  # the page and the recording are imported when a view is served
    from humanoid_prime.record.read import Recording
    from humanoid_prime.runtime.readout import JsonObject
    from humanoid_prime.view.page import PrimeView


def _port(p: argparse.ArgumentParser) -> None:
    p.add_argument("--port", type=whole(at_least=0, at_most=65535), default=DEFAULT_WEB_PORT, metavar="PORT",
                   help=f"serve on http://127.0.0.1:PORT/ (default {DEFAULT_WEB_PORT}; the next free port if taken)")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "view", help=summary("view"),
        description="Serve a page on 127.0.0.1 (offline: nothing is fetched from the internet) showing the robot "
                    "posed live, the mode with a button per mode (the same requests and refusals as prime "
                    "switch), the safety flags and each joint against its limits. It reads a running instance "
                    "over its control socket, or over DDS with --dds.")
    add_socket_option(p)
    add_dds_options(p, "read Prime's topics from the ROS 2 graph instead")
    _port(p)
    add_config_options(p)
    p.set_defaults(func=run_view)

    r = subparsers.add_parser(
        "replay", help=summary("replay"),
        description="Serve the 3D view and play a recording made with --record into it at its own pace "
                    "(--speed to change it), with its modes and joints. Playing starts when the first browser "
                    "opens the page; the page pauses, plays and seeks, and shows the time. Ctrl-C stops.")
    r.add_argument("recording", metavar="FILE.mcap")
    r.add_argument("--speed", type=real(above=0.0, at_most=100.0), default=1.0, metavar="X",
                   help="playback speed (default 1)")
    r.add_argument("--loop", action="store_true", help="start again at the end")
    r.add_argument("--no-wait", action="store_true", help="play at once, without waiting for a browser")
    _port(r)
    add_config_options(r)
    r.set_defaults(func=run_replay)


def run_view(args: argparse.Namespace) -> int:
    from humanoid_prime.view.page import PrimeView

    domain = dds_domain(args)
    robot = load_robot(args.hardware, use_sim=True)
    stop = threading.Event()
    source = None
    state: Callable[[], JsonObject]
    request_mode: Callable[[str], object]
    if domain is not None:
        from humanoid_prime.view.feeds import DdsSource

        source = DdsSource(robot, domain)
        state, request_mode, where = source, source.request_mode, "the ROS 2 graph"
    else:
        from humanoid_prime.runtime.socket import default_socket_path, request
        from humanoid_prime.view.feeds import socket_source

        path = args.socket or default_socket_path()
        request(path, {"op": "ping"}, timeout=2.0)  # nothing answers: one line now, not a page that never fills
        state, request_mode = socket_source(args.socket)
        where = f"the instance on {path}"
    try:
        with stop_on_signals(stop):
            view = PrimeView(robot, port=args.port, request_mode=request_mode, source=state)
            try:
                print(f"prime view: {view.url} (reading {where}; Ctrl-C stops)", flush=True)
                stop.wait()
            finally:
                view.close()
    finally:
        if source is not None:
            source.close()
    return 0


def run_replay(args: argparse.Namespace) -> int:
    from humanoid_prime.record.read import read_recording
    from humanoid_prime.view.page import PrimeView

    robot = load_robot(args.hardware, use_sim=True)
    recording = read_recording(args.recording, robot.names)
    stop = threading.Event()
    end = float(recording.time[-1])
    with stop_on_signals(stop):
        view = PrimeView(robot, port=args.port, title=f"Prime replay: {args.recording}", timeline=end)
        try:
            waiting = "" if args.no_wait else "; it plays when a browser opens the page"
            print(f"prime replay: {view.url} ({len(recording.time)} ticks, {end:.1f} s{waiting}; Ctrl-C stops)",
                  flush=True)
            if not args.no_wait:
                while not stop.is_set() and not view.browser.wait(0.2):
                    pass
            _play(recording, view, args.speed, args.loop, stop)
        finally:
            view.close()
    print(f"prime replay: {'stopped' if stop.is_set() else 'played'} {args.recording}", file=sys.stderr)
    return 0


FRAME_S = 1.0 / 60.0  # the replay redraws at most this often, whatever the recording's tick rate


def _play(recording: Recording, view: PrimeView, speed: float, loop: bool, stop: threading.Event) -> None:
    """Play ``recording`` into ``view`` (a replay's, with its timeline) from its start at ``speed``, following the
    page's pause and seek; to its end (again from the start with ``loop``) or until ``stop``."""
    times, timeline = recording.time, view.timeline
    if timeline is None:
        raise ValueError("a replay plays into a view with a timeline")
    mode_times = np.array([t for t, _ in recording.modes])
    position = 0.0  # seconds into the recording
    anchor = time.monotonic()
    while not stop.is_set():
        seek = timeline.seek_request()
        if seek is not None:
            position = min(max(seek, 0.0), float(times[-1]))
        if timeline.playing.is_set():
            now = time.monotonic()
            if seek is None:
                position += (now - anchor) * speed
            anchor = now
        else:
            anchor = time.monotonic()
        if position > times[-1]:
            if not loop:
                break
            position = 0.0
        k = max(int(np.searchsorted(times, position, side="right")) - 1, 0)
        m = int(np.searchsorted(mode_times, position, side="right")) - 1
        view.update(position=recording.position[k], mode=recording.modes[m][1] if m >= 0 else None,
                    effort=recording.effort[k].tolist())
        timeline.show(position)
        stop.wait(FRAME_S)
