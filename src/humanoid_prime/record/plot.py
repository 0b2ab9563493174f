"""``prime plot``: commanded against measured position and torque per joint, from a recording, to a PNG."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from humanoid_prime.files import atomic_write_bytes
from humanoid_prime.record.read import Recording

if TYPE_CHECKING:  # matplotlib is imported when a plot is drawn
    from matplotlib.axes import Axes

MODE_COLOURS = {"ZERO_TORQUE": "#dddddd", "DAMPING": "#c6dbef", "STANDBY": "#c7e9c0", "LOCOMOTION": "#fdd0a2",
                "REMOTE": "#dadaeb"}


def plot_recording(recording: Recording, joints: Sequence[str], output: str | Path) -> None:
    """One row per joint: position (measured, commanded target where the joint was stiff) and torque (measured,
    and the MIT law's commanded torque), over the run, with the modes shaded."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = [recording.index(joint) for joint in joints]
    torque = recording.commanded_torque()
    n = min(len(recording.command_time), len(recording.time))
    fig, axes = plt.subplots(len(columns), 2, figsize=(13, 2.2 * len(columns) + 0.6), sharex=True, squeeze=False)
    end = float(recording.time[-1]) if len(recording.time) else 0.0
    for row, j in enumerate(columns):
        position_axis, torque_axis = axes[row]
        for axis in (position_axis, torque_axis):
            _shade_modes(axis, recording, end, label=row == 0)
        position_axis.plot(recording.time, recording.position[:, j], color="#08519c", lw=1.2, label="measured")
        if n:
            stiff = recording.command[:n, 3, j] > 0
            target = np.where(stiff, recording.command[:n, 0, j], np.nan)
            position_axis.plot(recording.command_time[:n], target, color="#e6550d", lw=1.0, ls="--",
                               label="commanded (stiff)")
            torque_axis.plot(recording.command_time[:n], torque[:, j], color="#e6550d", lw=1.0, ls="--",
                             label="commanded (MIT law)")
        torque_axis.plot(recording.time, recording.effort[:, j], color="#08519c", lw=1.2, label="measured")
        position_axis.set_ylabel(f"{recording.names[j]}\nrad")
        torque_axis.set_ylabel("N m")
    axes[0][0].set_title("position", pad=14)
    axes[0][1].set_title("torque", pad=14)
    axes[0][0].legend(loc="upper right", fontsize=8)
    axes[0][1].legend(loc="upper right", fontsize=8)
    for axis in axes[-1]:
        axis.set_xlabel("s")
    fig.suptitle(f"{recording.path.name}: {len(recording.time)} ticks, modes shaded", fontsize=10)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    atomic_write_bytes(output, buffer.getvalue())


def _shade_modes(axis: Axes, recording: Recording, end: float, *, label: bool = False) -> None:
    if not recording.modes:
        return
    starts = [(max(t, 0.0), mode) for t, mode in recording.modes]
    for (start, mode), (stop, _) in zip(starts, [*starts[1:], (end, "")], strict=True):
        axis.axvspan(start, max(stop, start), color=MODE_COLOURS.get(mode, "#eeeeee"), alpha=0.6, lw=0)
        if label and stop > start:
            axis.text(start, 1.0, f" {mode}", transform=axis.get_xaxis_transform(), fontsize=7, va="bottom",
                      color="#444444")
