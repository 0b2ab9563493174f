"""``prime calibrate --auto --plot``: one row per joint that moved, position and commanded position (left axis) and
effort (right axis) against the robot's time, the contacts and the stops found marked."""

from __future__ import annotations

import io
from pathlib import Path

from humanoid_prime.calibration.report import AutoResult
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_bytes


def plot_auto(path: str | Path, result: AutoResult) -> None:
    """Draw the traces of ``result`` into a PNG at ``path`` (atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    traced = [j for j in result.asked if j in result.traces and result.traces[j].t]
    if not traced:
        raise PrimeError("no joint moved, so there is nothing to plot")
    fig, axes = plt.subplots(len(traced), 1, figsize=(10, 2.2 * len(traced) + 0.6), squeeze=False)
    for row, joint in enumerate(traced):
        trace, outcome = result.traces[joint], result.outcomes[joint]
        ax = axes[row][0]
        t0 = trace.t[0]
        t = [v - t0 for v in trace.t]
        ax.plot(t, trace.q, color="tab:blue", linewidth=1.2, label="position")
        ax.plot(t, trace.target, color="tab:blue", linewidth=0.8, linestyle="--", alpha=0.7,
                label="commanded position")
        ax.set_ylabel("rad")
        effort = ax.twinx()
        effort.plot(t, trace.effort, color="tab:orange", linewidth=0.8, label="effort")
        effort.set_ylabel("Nm")
        for when, _ in trace.contacts:
            ax.axvline(when - t0, color="tab:red", linewidth=0.8, alpha=0.6)
        for when, q in trace.stops:
            ax.plot([when - t0], [q], marker="o", color="tab:red", markersize=6)
            ax.annotate(f"stop {q:+.4f}", (when - t0, q), textcoords="offset points", xytext=(4, 4), fontsize="x-small")
        title = f"{joint}: {outcome.status}"
        if outcome.calibration is not None:
            title += (f", direction {outcome.calibration.direction:+d}, offset "
                      f"{outcome.calibration.homing_offset:+.4f} rad")
        ax.set_title(title, fontsize="small", loc="left")
        ax.grid(alpha=0.3)
        if row == 0:
            lines = ax.get_legend_handles_labels()[0] + effort.get_legend_handles_labels()[0]
            ax.legend(lines, [line.get_label() for line in lines], loc="upper right", fontsize="x-small",
                      ncol=3, frameon=False)
    axes[-1][0].set_xlabel("s since the joint began (robot time); red: contacts, dots: stops recorded")
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
