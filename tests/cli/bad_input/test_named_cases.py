"""Bad input, table-driven, by hand: every configuration file corrupted whole, semantic mistakes in otherwise
good files, and bad argument values the generated cases do not reach (conflicts, names, ranges). Each gets
exactly one line on stderr that names what was wrong and where, a non-zero exit, nothing started, and every file
as it was (run in-process by the bad-input harness)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from cli.bad_input.harness import check
from humanoid_prime.files import bundled

SENTINELS = {"out.yaml": b"sentinel: calibration\n", "summary.json": b"{\"sentinel\": true}\n",
             "plot.png": b"\x89PNG sentinel", "bench.json": b"[]\n"}

# --- configuration files: what each corruption writes, and what the one line must say -----------------

def _text(path: Path, text: str) -> None:
    path.write_text(text)


def _duplicate_top_key(path: Path, source: Path) -> None:
    text = source.read_text()
    first = next(line for line in text.splitlines() if line and not line.startswith(("#", " ")))
    path.write_text(text + "\n" + first + "\n")


def _nul_bytes(path: Path, source: Path) -> None:
    first, rest = source.read_bytes().split(b"\n", 1)
    path.write_bytes(first + b"\n\x00\x00" + rest)  # as a crash can leave a file: a run of NULs


CORRUPTIONS = {  # kind -> (how to make the file, what the error line must contain)
    "binary": (lambda p, s: p.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff\xfe\x00garbage"), "not UTF-8 text"),
    "empty": (lambda p, s: _text(p, ""), "empty"),
    "a list": (lambda p, s: _text(p, "- a\n- b\n"), "expected a mapping"),
    "bad syntax": (lambda p, s: _text(p, "joints: [\n  - a\n"), "malformed YAML"),
    "duplicate key": (_duplicate_top_key, "duplicate key"),
    "NUL bytes": (_nul_bytes, "line 2, column 1: a NUL byte"),
    "missing": (lambda p, s: None, "file not found"),
    "a folder": (lambda p, s: p.mkdir(), "is a folder"),
}
FILES = {"hardware": "prime_hardware.yaml", "calibration": "prime_calibration.yaml",
         "controllers": "prime_controllers.yaml"}
COMMANDS = {  # which commands load each file (each must fail before it touches a bus)
    "hardware": [["info"], ["gains", "--mode", "STANDBY"], ["bringup", "--summary", "{summary}"],
                 ["calibrate", "--output", "{out}"], ["sim", "--fast", "--duration", "0.1"]],
    "calibration": [["info"], ["calibration", "check", "{file}"], ["bringup", "--summary", "{summary}"],
                    ["calibration", "fold", "--out", "{tmp}/fold"]],
    "controllers": [["gains", "--mode", "STANDBY"], ["bringup", "--summary", "{summary}"],
                    ["sim", "--fast", "--duration", "0.1", "--summary", "{summary}"]],
}
CONFIG_CASES = [
    pytest.param(kind, which, command, id=f"{which}-{kind}-{'-'.join(command[:2 if 'calibration' in command else 1])}")
    for which in FILES for kind in CORRUPTIONS for command in COMMANDS[which]
]

# --- semantic mistakes in otherwise good files ----------------------------------------------------------

def _edit(name: str, change) -> object:
    def make(path: Path) -> None:
        data = yaml.safe_load(bundled(name).read_text())
        change(data)
        path.write_text(yaml.safe_dump(data, sort_keys=False))
    return make


def _params(data: dict, node: str) -> dict:
    return data[node]["ros__parameters"]


SEMANTIC_CASES = [  # (id, which file, how to change it, command, what the line must contain)
    ("standby kd 0", "controllers", lambda d: _params(d, "standby_controller").update(kd=0.0),
     ["bringup"], "standby_controller.ros__parameters.kd"),
    ("standby kd 1e9", "controllers", lambda d: _params(d, "standby_controller").update(kd=1e9),
     ["gains", "--mode", "STANDBY"], "standby_controller.ros__parameters.kd"),
    ("remote erob kd too small", "controllers", lambda d: _params(d, "remote_policy_controller").update(erob_kd=0.01),
     ["sim", "--fast", "--duration", "0.1"], "remote_policy_controller.ros__parameters.erob_kd"),
    ("damping kd 1e6", "controllers", lambda d: _params(d, "damping_controller").update(kd=1e6),
     ["bringup"], "damping_controller.ros__parameters.kd"),
    ("wrong controller type", "controllers",
     lambda d: _params(d, "controller_manager")["standby_controller"].update(type="my_pkg/Fancy"),
     ["gains", "--mode", "STANDBY"], "controller_manager.ros__parameters.standby_controller.type"),
    ("wrong mode field", "controllers", lambda d: _params(d, "standby_controller").update(mode="DAMPING"),
     ["gains", "--mode", "STANDBY"], "standby_controller.ros__parameters.mode"),
    ("action scale 1e6", "controllers", lambda d: _params(d, "locomotion_controller").update(action_scale=1e6),
     ["sim", "--fast", "--duration", "0.1"], "locomotion_controller.ros__parameters.action_scale"),
    ("physics rate 1", "controllers", lambda d: _params(d, "mujoco_simulation").update(physics_rate=1),
     ["sim", "--fast", "--duration", "0.1"], "mujoco_simulation.ros__parameters.physics_rate"),
    ("update rate above the eRob minimum cycle", "controllers",
     lambda d: _params(d, "controller_manager").update(update_rate=4000), ["bringup"],
     "controller_manager.ros__parameters.update_rate"),
    ("bringup rate 1e9", "controllers", lambda d: _params(d, "controller_manager").update(bringup_rate=1e9),
     ["bringup"], "controller_manager.ros__parameters.bringup_rate"),
    ("master -3", "hardware", lambda d: d["buses"]["ethercat"].update(master=-3), ["info"],
     "buses.ethercat.master"),
    ("ring position 1e9", "hardware", lambda d: d["joints"]["erob_slaves"].update(left_shoulder_pitch=10**9),
     ["info"], "joints.erob_slaves.left_shoulder_pitch"),
    ("ring positions with a gap", "hardware", lambda d: d["joints"]["erob_slaves"].update(right_wrist_yaw=12),
     ["info"], "joints.erob_slaves"),
    ("homing offset 1e6 rad", "calibration",
     lambda d: d["joints"]["left_elbow_pitch"].update(homing_offset=1e6), ["bringup"],
     "joints.left_elbow_pitch.homing_offset"),
    ("homing offset 1e6 rad in a fold", "calibration",
     lambda d: d["joints"]["left_elbow_pitch"].update(homing_offset=1e6), ["calibration", "fold", "--out", "{tmp}/f"],
     "joints.left_elbow_pitch.homing_offset"),
]

# --- command-line arguments -------------------------------------------------------------------------

ARGUMENT_CASES = [  # (id, arguments, what the line must contain)
    ("limp damping inf", ["limp", "4", "inf", "--socket", "{tmp}/none.sock"], "DAMPING"),
    ("limp damping 1e9", ["limp", "4", "1e9", "--socket", "{tmp}/none.sock"], "DAMPING"),
    ("limp damping that rounds to no damping", ["limp", "4", "0.001", "--socket", "{tmp}/none.sock"], "DAMPING"),
    ("limp seconds -1", ["limp", "4", "--seconds", "-1", "--socket", "{tmp}/none.sock"], "--seconds"),
    ("limp seconds nan", ["limp", "4", "--seconds", "nan", "--socket", "{tmp}/none.sock"], "--seconds"),
    ("limp ring -1", ["limp", "-1", "--socket", "{tmp}/none.sock"], "RING_POS"),
    ("dc lock cycles -5", ["bringup", "--emulate", "--dc-lock-cycles", "-5", "--summary", "{summary}"],
     "--dc-lock-cycles"),
    ("mailbox latency nan", ["bringup", "--emulate", "--mailbox-latency", "nan", "--summary", "{summary}"],
     "--mailbox-latency"),
    ("bringup rate 0", ["bringup", "--bringup-rate", "0", "--summary", "{summary}"], "--bringup-rate"),
    ("bringup rate 1e9", ["bringup", "--bringup-rate", "1e9", "--summary", "{summary}"], "--bringup-rate"),
    ("dwell -1", ["bringup", "--sequence", "DAMPING", "--dwell", "-1"], "--dwell"),
    ("empty sequence", ["bringup", "--sequence", ""], "--sequence"),
    ("unknown mode in a sequence", ["bringup", "--sequence", "DAMPING,DANCE"], "DANCE"),
    ("duration 0", ["bringup", "--duration", "0"], "--duration"),
    ("control rate above the eRob's minimum cycle", ["bringup", "--rate", "5000"], "--rate"),
    ("control rate 0", ["bringup", "--rate", "0"], "--rate"),
    ("a cpu this machine has not", ["bringup", "--cpu", "4096"], "--cpu"),
    ("a cpu to pin a loop that is not real time", ["bringup", "--cpu", "0", "--no-realtime"], "--cpu"),
    ("soak minutes -1", ["bench", "soak", "--minutes", "-1"], "--minutes"),
    ("load test of a joint Prime has not", ["bringup", "--emulate", "--load-test", "left_toe",
                                            "--summary", "{summary}"], "left_toe"),
    ("load test of a wrist", ["bringup", "--emulate", "--load-test", "left_wrist_roll",
                              "--summary", "{summary}"], "left_wrist_roll"),
    ("emulator tunable without --emulate", ["bringup", "--dc-lock-cycles", "10"], "--dc-lock-cycles"),
    ("summary is a folder", ["bringup", "--summary", "{tmp}"], "--summary"),
    ("calibrate output is a folder", ["calibrate", "--output", "{tmp}"], "--output"),
    ("calibrate plot under a file", ["calibrate", "--plot", "{summary}/plot.png"], "--plot"),
    ("sim summary is a folder", ["sim", "--fast", "--duration", "0.1", "--summary", "{tmp}"], "--summary"),
    ("sim duration -1", ["sim", "--duration", "-1"], "--duration"),
    ("sim unknown mode", ["sim", "--mode", "DANCE", "--duration", "0.1"], "DANCE"),
    ("web view of an emulated bringup", ["bringup", "--emulate", "--web"], "run `prime view --socket"),
    ("web view of an emulated calibration", ["calibrate", "--emulate", "--web", "0"], "run `prime view --socket"),
    ("scripted joint unknown", ["calibrate", "--emulate", "--scripted", "left_toe", "--output", "{tmp}/cal.yaml"],
     "left_toe"),
    ("can ids open range", ["can", "discover", "--ids", "1-", "--interface", "virtual"], "--ids"),
    ("can ids out of range", ["can", "discover", "--ids", "300", "--interface", "virtual"], "--ids"),
    ("can seconds inf", ["can", "monitor", "--seconds", "inf", "--interface", "virtual"], "--seconds"),
    ("emulate on a NIC that does not exist", ["emulate", "ec", "--interface", "nonexistent0"], "nonexistent0"),
    ("sdo write of a negative untyped value", ["ec", "sdo", "write", "3", "0x2382:01", "-5",
                                               "--interface", "nonexistent0"], "-5"),
    ("sdo address garbage", ["ec", "sdo", "read", "3", "0x23zz:01", "--interface", "nonexistent0"], "0x23zz"),
    ("gains kd negative", ["gains", "--kp", "20", "--kd", "-1"], "--kd"),
    ("gains efficiency 2", ["gains", "--mode", "STANDBY", "--efficiency", "2"], "--efficiency"),
    ("decode garbage", ["decode", "error", "0xZZ"], "0xZZ"),
    ("switch to an unknown mode", ["switch", "DANCE", "--socket", "{tmp}/none.sock"], "DANCE"),
    ("bench unknown suite", ["bench", "--only", "nope", "--output", "{bench}"], "nope"),
    ("flip an unknown joint", ["calibration", "flip", "left_toe", "--calibration", "{tmp}/cal.yaml"], "left_toe"),
]


@pytest.fixture
def place(tmp_path):
    """A folder with output files that must stay as they are, one a good calibration (a calibration run's
    output is also its prior)."""
    for name, data in {**SENTINELS, "cal.yaml": bundled("prime_calibration.yaml").read_bytes()}.items():
        (tmp_path / name).write_bytes(data)
    return tmp_path


def run(place: Path, monkeypatch, args: list[str], *needles: str) -> None:
    values = {"tmp": str(place), "out": str(place / "out.yaml"), "summary": str(place / "summary.json"),
              "plot": str(place / "plot.png"), "bench": str(place / "bench.json"), "file": str(place / "bad")}
    check([a.format(**values) for a in args], place, monkeypatch, needles=needles)
    assert not list(place.glob(".*.tmp")), "a temporary file was left behind"


@pytest.mark.parametrize("kind, which, command", CONFIG_CASES)
def test_a_corrupt_configuration_file_is_one_line_naming_the_file(place, monkeypatch, kind, which, command):
    make, says = CORRUPTIONS[kind]
    bad = place / "bad"
    make(bad, bundled(FILES[which]))
    option = [] if command[:2] == ["calibration", "check"] else [f"--{which}", str(bad)]
    run(place, monkeypatch, [*command, *option], str(bad), says)


@pytest.mark.parametrize("which, change, command, names",
                         [pytest.param(w, c, cmd, n, id=i) for i, w, c, cmd, n in SEMANTIC_CASES])
def test_a_configuration_mistake_is_refused_at_load_naming_the_file_and_key(place, monkeypatch, which, change,
                                                                             command, names):
    bad = place / f"bad_{which}.yaml"
    _edit(FILES[which], change)(bad)
    run(place, monkeypatch, [*command, f"--{which}", str(bad)], str(bad), names)


@pytest.mark.parametrize("args, names", [pytest.param(a, n, id=i) for i, a, n in ARGUMENT_CASES])
def test_a_bad_argument_is_one_line_naming_it(place, monkeypatch, args, names):
    run(place, monkeypatch, args, names)
