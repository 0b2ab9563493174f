#!/usr/bin/env python3
"""Regenerate the bundled locomotion policy ``standby_policy.onnx`` (deterministic: same file every run).

The policy is a two-layer MLP (observation -> 16 tanh units -> 14 actions) whose weights are designed
rather than trained: the hidden layer is a ring of 16 phase detectors, tanh(g*sin(phase + theta_k)),
and the output layer recombines them into one sinusoid per joint, so the arms swing gently around the
default pose, left and right in antiphase, one cycle per ``PERIOD_S``. A weak, fixed coupling from
the joint state keeps it an ordinary observation-to-action network.

    .venv/bin/python tools/make_policy.py [--output PATH]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from humanoid_prime.config.hardware import load_hardware
from humanoid_prime.control.policy import export_mlp

OUTPUT = Path(__file__).resolve().parents[1] / "src" / "humanoid_prime" / "data" / "standby_policy.onnx"
OBSERVATION = ("joint_pos_rel", "joint_vel", "last_action", "phase_sin", "phase_cos")
PERIOD_S = 3.0
HIDDEN = 16
GAIN = 0.8  # phase-detector input gain: mostly linear, slightly rounded peaks
ACTION_SCALE = 0.25  # rad per action unit, as locomotion_controller.action_scale in prime_controllers.yaml
COUPLING = 0.01  # weight scale of the joint-state inputs
# Swing amplitude (rad) and phase lag (rad) per joint of the left arm; the right arm runs half a cycle later.
SWING = {
    "shoulder_pitch": (0.12, 0.0),
    "shoulder_roll": (0.04, 0.0),
    "shoulder_yaw": (0.05, 0.5 * math.pi),
    "elbow_pitch": (0.15, -0.5 * math.pi),
    "wrist_roll": (0.10, 0.5 * math.pi),
    "wrist_pitch": (0.08, 0.0),
    "wrist_yaw": (0.08, math.pi),
}


def design(joint_names: tuple[str, ...]) -> list[tuple[np.ndarray, np.ndarray]]:
    n = len(joint_names)
    size = 3 * n + 2
    theta = 2.0 * math.pi * np.arange(HIDDEN) / HIDDEN
    w1 = np.zeros((HIDDEN, size))
    # A fixed, irregular pattern (golden-angle sine) for the joint-state inputs.
    w1[:, : 3 * n] = COUPLING * np.sin(2.399963 * np.arange(HIDDEN * 3 * n).reshape(HIDDEN, 3 * n) + 1.0)
    w1[:, 3 * n] = GAIN * np.cos(theta)  # sin(phase) input
    w1[:, 3 * n + 1] = GAIN * np.sin(theta)  # cos(phase) input: unit k sees GAIN*sin(phase + theta_k)
    w2 = np.zeros((n, HIDDEN))
    for j, name in enumerate(joint_names):
        side, joint = name.split("_", 1)
        amplitude, lag = SWING[joint]
        if side == "right":
            lag += math.pi
        # sum_k cos(theta_k - lag) * sin(phase + theta_k) = (HIDDEN / 2) * sin(phase + lag)
        w2[j] = (2.0 * amplitude / ACTION_SCALE / (HIDDEN * GAIN)) * np.cos(theta - lag)
    return [(w1, np.zeros(HIDDEN)), (w2, np.zeros(n))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=OUTPUT, help=f"where to write (default: {OUTPUT})")
    args = parser.parse_args()
    joint_names = load_hardware().all_joints
    model = export_mlp(design(joint_names), joint_names, OBSERVATION, PERIOD_S)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_bytes(model.SerializeToString())
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
