"""ONNX policies: the bundled one, its generator, export and the checks made when loading."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest

from humanoid_prime.control.policy import Policy, export_mlp
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import bundled

ROOT = Path(__file__).resolve().parents[2]
TERMS = ("joint_pos_rel", "joint_vel", "last_action", "phase_sin", "phase_cos")


def observations(count: int) -> np.ndarray:
    """A fixed spread of observations (no randomness)."""
    grid = np.arange(count * 44, dtype=np.float64).reshape(count, 44)
    return (0.3 * np.sin(0.37 * grid)).astype(np.float32)


def infer(policy: Policy, observation: np.ndarray) -> np.ndarray:
    policy.observation[0] = observation
    return policy.run().copy()


def save(model, path: Path) -> Path:
    path.write_bytes(model.SerializeToString())
    return path


def test_the_generator_reproduces_the_bundled_policy(robot, tmp_path):
    out = tmp_path / "regenerated.onnx"
    subprocess.run([sys.executable, str(ROOT / "tools" / "make_policy.py"), "--output", str(out)], check=True,
                   capture_output=True)
    shipped, regenerated = Policy(bundled("standby_policy.onnx"), robot.names), Policy(out, robot.names)
    for observation in observations(32):
        np.testing.assert_array_equal(infer(regenerated, observation), infer(shipped, observation))


def test_the_bundled_policy_swings_the_arms_gently_in_antiphase_every_3_s(robot):
    policy = Policy(bundled("standby_policy.onnx"), robot.names)
    zeros = np.zeros(14)
    times = np.arange(0.0, 6.0, 0.05)
    swing = []
    for t in times:
        policy.pack(zeros, zeros, zeros, t)
        swing.append(0.25 * policy.run())  # rad, with the configured action_scale
    swing = np.array(swing)
    amplitude = np.abs(swing).max(axis=0)
    assert np.all((amplitude > 0.02) & (amplitude < 0.15))
    np.testing.assert_allclose(swing[:60], swing[60:], atol=1e-6)  # 3 s period
    left, right = swing[:, robot.index("left_shoulder_pitch")], swing[:, robot.index("right_shoulder_pitch")]
    assert np.corrcoef(left, right)[0, 1] < -0.99


def test_an_exported_mlp_computes_the_numpy_forward_pass(robot, tmp_path):
    w1 = np.cos(np.arange(8 * 44).reshape(8, 44)) * 0.2
    b1 = np.linspace(-0.5, 0.5, 8)
    w2 = np.sin(np.arange(14 * 8).reshape(14, 8))
    b2 = np.linspace(0.0, 1.3, 14)
    policy = Policy(save(export_mlp([(w1, b1), (w2, b2)], robot.names, TERMS, 2.0), tmp_path / "p.onnx"),
                    robot.names)
    for observation in observations(4):
        expected = w2 @ np.tanh(w1 @ observation.astype(np.float64) + b1) + b2
        np.testing.assert_allclose(infer(policy, observation), expected, rtol=1e-5, atol=1e-5)


def test_pack_fills_only_the_declared_terms_in_their_order(robot, tmp_path):
    terms = ("phase_cos", "joint_vel")
    model = export_mlp([(np.zeros((14, 15)), np.zeros(14))], robot.names, terms, 4.0)
    policy = Policy(save(model, tmp_path / "p.onnx"), robot.names)
    policy.pack(np.full(14, 9.0), np.arange(14.0), np.full(14, 7.0), 1.0)  # a quarter period
    np.testing.assert_allclose(policy.observation[0], [0.0, *range(14)], atol=1e-6)


def test_a_policy_for_another_joint_order_is_refused(robot, tmp_path):
    names = (*robot.names[1:], robot.names[0])
    path = save(export_mlp([(np.zeros((14, 44)), np.zeros(14))], names, TERMS, 1.0), tmp_path / "p.onnx")
    with pytest.raises(PrimeError, match="policy made for joints left_shoulder_roll, .*canonical order"):
        Policy(path, robot.names)


def test_a_policy_with_the_wrong_number_of_actions_is_refused(robot, tmp_path):
    model = export_mlp([(np.zeros((13, 41)), np.zeros(13))], robot.names[:13], TERMS, 1.0)
    onnx.helper.set_model_props(model, {"joint_names": ",".join(robot.names), "observation": ",".join(TERMS),
                                        "phase_period_s": "1.0"})
    model.graph.input[0].type.tensor_type.shape.dim[1].dim_value = 44
    w0 = next(t for t in model.graph.initializer if t.name == "w0")
    w0.CopyFrom(onnx.numpy_helper.from_array(np.zeros((13, 44), np.float32), "w0"))
    with pytest.raises(PrimeError, match=r"output 'actions' has shape \(1, 13\), expected \(1, 14\)"):
        Policy(save(model, tmp_path / "p.onnx"), robot.names)


def test_a_phase_observation_without_a_period_is_refused(robot, tmp_path):
    model = export_mlp([(np.zeros((14, 44)), np.zeros(14))], robot.names, TERMS, 1.0)
    onnx.helper.set_model_props(model, {"joint_names": ",".join(robot.names), "observation": ",".join(TERMS)})
    with pytest.raises(PrimeError, match="'phase_period_s' is missing"):
        Policy(save(model, tmp_path / "p.onnx"), robot.names)


def test_an_unknown_observation_term_is_refused(robot, tmp_path):
    model = export_mlp([(np.zeros((14, 44)), np.zeros(14))], robot.names, TERMS, 1.0)
    onnx.helper.set_model_props(model, {"joint_names": ",".join(robot.names), "phase_period_s": "1.0",
                                        "observation": "joint_pos_rel,joint_vel,last_action,base_height,phase"})
    with pytest.raises(PrimeError, match="unknown observation term 'base_height'"):
        Policy(save(model, tmp_path / "p.onnx"), robot.names)


def test_a_file_that_is_not_a_model_is_refused(robot, tmp_path):
    path = tmp_path / "policy.onnx"
    path.write_text("not a model")
    with pytest.raises(PrimeError, match="policy.onnx: cannot load the policy"):
        Policy(path, robot.names)


def test_export_refuses_layers_that_do_not_chain(robot):
    with pytest.raises(ValueError, match="layer 1: weight \\(14, 9\\)"):
        export_mlp([(np.zeros((8, 44)), np.zeros(8)), (np.zeros((14, 9)), np.zeros(14))], robot.names, TERMS, 1.0)
