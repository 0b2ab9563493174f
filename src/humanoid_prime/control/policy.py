"""ONNX policies: export an MLP from NumPy weights, load a policy, pack its observation, run it.

A policy file is self-describing through its metadata:
- ``joint_names``: the canonical joint order it was made for (comma-separated; must match the robot),
- ``observation``: the observation terms in input order (comma-separated, from ``OBSERVATION_TERMS``),
- ``phase_period_s``: the period of the phase clock, when the observation uses ``phase_sin``/``phase_cos``.
Input: one float32 tensor ``[1, observation size]``; output: one float32 tensor ``[1, joints]`` (actions).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from humanoid_prime.errors import ControllerError, PrimeError

if TYPE_CHECKING:
    import onnx

# Term -> size; "n" is one value per joint.
OBSERVATION_TERMS: dict[str, str | int] = {
    "joint_pos_rel": "n",   # measured position minus the default pose (rad)
    "joint_vel": "n",       # measured velocity (rad/s)
    "last_action": "n",     # the previous action, unscaled
    "phase_sin": 1,         # sin(2*pi*t / phase_period_s), t from the mode's entry
    "phase_cos": 1,
}
INPUT_NAME = "observation"
OUTPUT_NAME = "actions"
OPSET = 17
IR_VERSION = 8  # readable by onnxruntime >= 1.17


def observation_size(terms: Sequence[str], n: int) -> int:
    size = 0
    for term in terms:
        if term not in OBSERVATION_TERMS:
            raise ValueError(f"unknown observation term {term!r}; known terms: {', '.join(OBSERVATION_TERMS)}")
        width = OBSERVATION_TERMS[term]
        size += n if width == "n" else int(width)
    return size


def export_mlp(layers: Sequence[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]], joint_names: Sequence[str],
               observation: Sequence[str], phase_period_s: float | None = None) -> onnx.ModelProto:
    """An ONNX model computing ``W_k @ tanh(... tanh(W_1 @ obs + b_1) ...) + b_k`` from (W, b) pairs.

    ``W`` has shape (outputs, inputs); the last layer must have one output per joint.
    """
    import onnx  # imported here: only exporting needs it
    from onnx import TensorProto, helper, numpy_helper

    n = len(joint_names)
    size = observation_size(observation, n)
    if any(term.startswith("phase_") for term in observation) and not (phase_period_s and phase_period_s > 0):
        raise ValueError("a phase observation needs phase_period_s > 0")
    nodes, initializers = [], []
    x, width = INPUT_NAME, size
    for k, (weight, bias) in enumerate(layers):
        weight = np.asarray(weight, dtype=np.float32)
        bias = np.asarray(bias, dtype=np.float32)
        if weight.ndim != 2 or weight.shape[1] != width or bias.shape != (weight.shape[0],):
            raise ValueError(f"layer {k}: weight {weight.shape} and bias {bias.shape} do not take {width} inputs")
        last = k == len(layers) - 1
        initializers += [numpy_helper.from_array(weight, f"w{k}"), numpy_helper.from_array(bias, f"b{k}")]
        y = OUTPUT_NAME if last else f"z{k}"
        nodes.append(helper.make_node("Gemm", [x, f"w{k}", f"b{k}"], [y], transB=1))
        if not last:
            nodes.append(helper.make_node("Tanh", [y], [f"h{k}"]))
            y = f"h{k}"
        x, width = y, weight.shape[0]
    if width != n:
        raise ValueError(f"the last layer has {width} outputs, expected one per joint ({n})")
    graph = helper.make_graph(
        nodes, "policy",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, [1, size])],
        [helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.FLOAT, [1, n])],
        initializers,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="humanoid_prime", producer_version="1")
    model.ir_version = IR_VERSION
    props = {"joint_names": ",".join(joint_names), "observation": ",".join(observation)}
    if phase_period_s:
        props["phase_period_s"] = repr(float(phase_period_s))
    helper.set_model_props(model, props)
    onnx.checker.check_model(model)
    return model


class Policy:
    """A loaded policy with a preallocated observation and action; ``run`` is one inference."""

    def __init__(self, path: str | Path, joint_names: Sequence[str]) -> None:
        import onnxruntime as ort

        self.path = Path(path)
        n = len(joint_names)
        options = ort.SessionOptions()
        # One thread, no spinning: the control loop shares two cores with the buses.
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self.session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:
            raise PrimeError(f"{self.path}: cannot load the policy: {exc}") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        made_for = tuple(meta.get("joint_names", "").split(","))
        if made_for != tuple(joint_names):
            raise PrimeError(f"{self.path}: policy made for joints {', '.join(made_for) or '(none given)'}; "
                             f"this robot has {', '.join(joint_names)} (export the policy with the canonical order)")
        self.terms = tuple(t for t in meta.get("observation", "").split(",") if t)
        try:
            size = observation_size(self.terms, n)
        except ValueError as exc:
            raise PrimeError(f"{self.path}: metadata 'observation': {exc}") from None
        self.phase_period = 0.0
        if {"phase_sin", "phase_cos"} & set(self.terms):
            try:
                self.phase_period = float(meta["phase_period_s"])
            except (KeyError, ValueError):
                self.phase_period = 0.0
            if not self.phase_period > 0.0:
                raise PrimeError(f"{self.path}: the observation uses the phase but metadata 'phase_period_s' "
                                 "is missing or not a positive number")
        (inp,) = self.session.get_inputs()
        if inp.shape[-1] != size:
            raise PrimeError(f"{self.path}: input {inp.name!r} has shape {inp.shape}; the declared observation "
                             f"({', '.join(self.terms)}) has {size} values")
        self.observation = np.zeros((1, size), dtype=np.float32)
        output = self.session.get_outputs()[0]
        probe = self.session.run([output.name], {inp.name: self.observation})[0]
        if probe.shape != (1, n):
            raise PrimeError(f"{self.path}: output {output.name!r} has shape {probe.shape}, expected (1, {n})")
        self.actions: npt.NDArray[np.float32] = np.zeros((1, n), dtype=np.float32)
        # Bound once: inference reads self.observation and writes self.actions in place.
        self._binding = self.session.io_binding()
        self._binding.bind_cpu_input(inp.name, self.observation)
        self._binding.bind_output(output.name, "cpu", 0, np.float32, list(self.actions.shape),
                                  self.actions.ctypes.data)
        self._views: dict[str, npt.NDArray[np.float32]] = {}
        start = 0
        for term in self.terms:
            width = n if OBSERVATION_TERMS[term] == "n" else int(OBSERVATION_TERMS[term])
            self._views[term] = self.observation[0, start:start + width]
            start += width
        self._pos = self._views.get("joint_pos_rel")
        self._vel = self._views.get("joint_vel")
        self._last = self._views.get("last_action")
        self._sin = self._views.get("phase_sin")
        self._cos = self._views.get("phase_cos")

    def pack(self, joint_pos_rel: npt.NDArray[np.float64], joint_vel: npt.NDArray[np.float64],
             last_action: npt.NDArray[np.float64], time: float) -> None:
        """Write the declared observation terms; ``time`` (s since entry) drives the phase clock."""
        if self._pos is not None:
            np.copyto(self._pos, joint_pos_rel, casting="same_kind")
        if self._vel is not None:
            np.copyto(self._vel, joint_vel, casting="same_kind")
        if self._last is not None:
            np.copyto(self._last, last_action, casting="same_kind")
        if self.phase_period:
            phase = 2.0 * math.pi * time / self.phase_period
            if self._sin is not None:
                self._sin[0] = math.sin(phase)
            if self._cos is not None:
                self._cos[0] = math.cos(phase)

    def run(self) -> npt.NDArray[np.float32]:
        """Infer from the packed observation; returns the action row (a view, overwritten next call)."""
        try:
            self.session.run_with_iobinding(self._binding)
        except Exception as exc:
            raise ControllerError(f"policy inference failed: {exc}") from None
        action: npt.NDArray[np.float32] = self.actions[0]
        return action
