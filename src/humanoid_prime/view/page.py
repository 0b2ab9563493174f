"""The browser page of Prime: the robot posed live, the active mode and a button per mode, the time run and the
loop rate, the safety flags, each joint's position against its limits, its measured torque and its drive's state
(statusword and AL state, "—" where it has no such drive) and, during a calibration, each joint's swept range.

Served by viser on 127.0.0.1 only, entirely from the installed package (no CDN, no telemetry: the share
button and the logo link are off). The page is fed through ``update`` from any thread; a view thread redraws
at ``rate`` Hz, so nothing here runs on the control thread. Mode buttons call ``request_mode`` with the mode's
name: the same path, with the same refusals, as ``prime switch``.
"""

from __future__ import annotations

import contextlib
import html
import io
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.hardware import DriveStatus
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.readout import NONE, DriveWords, JsonObject, drive_from_dict, loop_words
from humanoid_prime.view.scene import RobotScene

if TYPE_CHECKING:  # viser is imported when a page is served
    from viser import GuiApi, GuiEvent, GuiInputHandle, GuiMultiSliderHandle, GuiSliderHandle

T = TypeVar("T")
REDRAW_HZ = 20.0
LEVEL_MARK = {"WARN": "⚠️", "ERROR": "⛔"}


def drive_table(robot: Robot, effort: list[float | None] | None, drives: dict[str, DriveStatus]) -> str:
    """Per joint, its measured torque and its drive's statusword, CiA402 state and AL state, as an HTML table."""
    rows = []
    for joint in robot.joints:
        tau = effort[joint.index] if effort is not None else None
        words = DriveWords.of(drives.get(joint.name))
        cells = (joint.name, NONE if tau is None or tau != tau else f"{tau:+.2f}", words.statusword, words.state,
                 words.al_state)
        rows.append("<tr>" + "".join(f"<td{' align=right' if k == 1 else ''}>{html.escape(c)}</td>"
                                     for k, c in enumerate(cells)) + "</tr>")
    head = "".join(f"<th align=left>{name}</th>" for name in ("joint", "tau Nm", "statusword", "drive", "AL"))
    return f'<table style="font-size:0.8em;font-family:monospace"><tr>{head}</tr>{"".join(rows)}</table>'


class Timeline:
    """A replay's controls on the page: play/pause, a time slider to seek with, and the time readout. The player
    reads ``playing`` and takes ``seek_request()``; a person's drag of the slider is a seek, the player's own
    moves of it are not."""

    def __init__(self, gui: GuiApi, duration: float) -> None:
        self.duration = duration
        self.playing = threading.Event()
        self.playing.set()
        self._seek: float | None = None
        self._lock = threading.Lock()
        self._button = gui.add_button("pause")
        self._button.on_click(lambda event: self.toggle())
        self._slider = gui.add_slider("time (s)", min=0.0, max=max(duration, 0.01), step=0.01, initial_value=0.0)
        self._slider.on_update(self._on_slider)
        self._readout = gui.add_markdown(self._words(0.0))

    def toggle(self) -> None:
        if self.playing.is_set():
            self.playing.clear()
            self._button.label = "play"
        else:
            self.playing.set()
            self._button.label = "pause"

    def _on_slider(self, event: GuiEvent[GuiSliderHandle[float]]) -> None:
        if event.client is None:  # the player moved it
            return
        with self._lock:
            self._seek = float(event.target.value)

    def seek_request(self) -> float | None:
        """The time a person asked to go to since the last call, if any."""
        with self._lock:
            seek, self._seek = self._seek, None
        return seek

    def show(self, t: float) -> None:
        _set(self._slider, float(min(max(t, 0.0), self._slider.max)))
        self._readout.content = self._words(t)

    def _words(self, t: float) -> str:
        return f"**t** {t:6.2f} s of {self.duration:.2f} s" + ("" if self.playing.is_set() else " (paused)")


def _set(handle: GuiInputHandle[T], value: T) -> None:
    """``handle.value = value``: viser defines that setter apart from its getter, where mypy does not see it."""
    handle.value = value  # type: ignore[misc]


def _number(value: object) -> float | None:
    return float(value) if isinstance(value, (int, float)) else None


class PrimeView:
    def __init__(self, robot: Robot, *, port: int = 8080, host: str = "127.0.0.1", title: str = "Prime",
                 request_mode: Callable[[str], object] | None = None, source: Callable[[], JsonObject] | None = None,
                 sweeps: bool = False, model_path: str | Path | None = None, rate: float = REDRAW_HZ,
                 timeline: float | None = None) -> None:
        import viser

        self.robot = robot
        self.request_mode = request_mode
        self.source = source  # polled by the view thread for the latest state (else: fed through update)
        with contextlib.redirect_stdout(io.StringIO()):  # viser announces itself on stdout; ours says the URL
            try:
                self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
            except OSError as exc:
                raise PrimeError(f"cannot serve the view on {host}:{port}: {exc.strerror or exc}") from None
        self.port = self.server.get_port()  # viser moves on to the next free port when this one is taken
        self.url = f"http://{host}:{self.port}/"
        server = self.server
        server.gui.configure_theme(show_share_button=False, show_logo=False, control_width="large")
        server.initial_camera.position = (1.3, -1.1, 1.6)  # in front of the torso, a little above the shoulders
        server.initial_camera.look_at = (0.0, 0.0, 1.05)
        self.scene = RobotScene(server, robot, model_path)
        gui = server.gui
        self.browser = threading.Event()  # a browser has opened the page
        server.on_client_connect(lambda client: self.browser.set())
        # A replay's controls (its length in seconds), above the rest; None: a live run.
        self.timeline = None
        if timeline is not None:
            with gui.add_folder("replay"):
                self.timeline = Timeline(gui, timeline)
        self._mode = gui.add_markdown("**mode** —")
        self._buttons = gui.add_button_group("switch to", [mode.value for mode in Mode],
                                             disabled=request_mode is None)
        self._buttons.on_click(lambda event: self._on_button(event.target.value))
        self._answer = gui.add_markdown("")
        self._loop = gui.add_markdown(loop_words(None, None, None))
        with gui.add_folder("safety"):
            self._safety = gui.add_markdown("ok")
        with gui.add_folder("drives: torque and state"):
            self._drives = gui.add_html(drive_table(robot, None, {}))
        with gui.add_folder("joints: position within limits (rad)"):
            self._joints = [gui.add_slider(j.name, min=j.lower, max=j.upper, step=0.001,
                                           initial_value=float(np.clip(0.0, j.lower, j.upper)), disabled=True)
                            for j in robot.joints]
        self._sweeps: list[GuiMultiSliderHandle[float]] = []
        if sweeps:
            with gui.add_folder("calibration: swept range within limits (rad)"):
                self._sweeps = [gui.add_multi_slider(f"{j.name} swept", min=j.lower, max=j.upper, step=0.001,
                                                     initial_value=(j.lower, j.lower), disabled=True)
                                for j in robot.joints]
        self._lock = threading.Lock()
        self._latest: JsonObject = {}
        self._version = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._redraw, args=(1.0 / rate,), name="view", daemon=True)
        self._thread.start()

    # ---- fed from anywhere ---------------------------------------------------------------------------

    def update(self, **latest: object) -> None:
        """Keep the newest of ``position`` (14 rad), ``mode`` (str), ``flags`` and ``levels`` (dicts keyed by
        flag), ``sweeps`` (14 (min, max) pairs), and what ``Readout.as_dict`` gives (``elapsed_s``, ``rate_hz``,
        ``update_rate_hz``, ``effort``, ``drives``); the view thread draws them."""
        with self._lock:
            self._latest.update(latest)
            self._version += 1

    def _on_button(self, mode: str) -> None:  # viser's thread
        if self.request_mode is None:
            return
        try:
            self.request_mode(mode)
        except Exception as exc:  # the same refusal `prime switch` prints, on the page
            self._answer.content = f"**{mode}** refused: {exc}"
        else:
            self._answer.content = f"asked for **{mode}**"

    # ---- the view thread -----------------------------------------------------------------------------

    def _redraw(self, period: float) -> None:
        seen = -1
        while not self._stop.wait(period):
            if self.source is not None:
                try:
                    self.update(**self.source())
                except Exception as exc:  # the run went away (or is not up yet): say so, keep trying
                    self.update(mode=f"not connected ({exc})")
            with self._lock:
                if self._version == seen:
                    continue
                seen = self._version
                latest = dict(self._latest)
            try:
                self._draw(latest)
            except Exception:  # a browser that went away mid-update; the next frame redraws everything
                continue

    def _draw(self, latest: Mapping[str, object]) -> None:
        """Draw what ``latest`` holds; a value of another shape than ``update`` names (a socket's garbled
        answer) is left undrawn."""
        position = latest.get("position")
        if isinstance(position, (list, tuple, np.ndarray)):
            q = np.asarray(position, dtype=np.float64)
            self.scene.pose(q)
            for slider, joint, value in zip(self._joints, self.robot.joints, q, strict=True):
                if value == value:
                    _set(slider, float(np.clip(value, joint.lower, joint.upper)))
        if "mode" in latest:
            self._mode.content = f"**mode** {latest['mode'] or '—'}"
        flags, levels = latest.get("flags"), latest.get("levels")
        if isinstance(flags, dict):
            levels = levels if isinstance(levels, dict) else {}
            lines = [f"- {LEVEL_MARK.get(str(levels.get(key, 'ERROR')), '')} `{key}`: {text}"
                     for key, text in sorted(flags.items())]
            self._safety.content = "\n".join(lines) or "ok"
        if "rate_hz" in latest or "elapsed_s" in latest:
            self._loop.content = loop_words(_number(latest.get("elapsed_s")), _number(latest.get("rate_hz")),
                                            _number(latest.get("update_rate_hz")))
        if "effort" in latest or "drives" in latest:
            effort, entries = latest.get("effort"), latest.get("drives")
            drives = {joint: drive_from_dict(joint, entry) for joint, entry in entries.items()} \
                if isinstance(entries, dict) else {}
            self._drives.content = drive_table(self.robot, effort if isinstance(effort, list) else None, drives)
        sweeps = latest.get("sweeps")
        if isinstance(sweeps, (list, tuple, np.ndarray)) and self._sweeps:
            for sweep, joint, (low, high) in zip(self._sweeps, self.robot.joints, sweeps, strict=True):
                if low <= high:
                    _set(sweep, (float(np.clip(low, joint.lower, joint.upper)),
                                 float(np.clip(high, joint.lower, joint.upper))))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()
