"""Recordings: what `prime sim --record` writes is read back by an independent reader (rosbags) with the
expected messages per topic, ROS 2 schemas and rosbag2's channel metadata; a run stopped by a signal still
leaves a readable file; `prime plot` draws it."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from doubles.process import popen
from humanoid_prime.files import bundled

PRIME = [sys.executable, "-m", "humanoid_prime"]
REPOSITORY = Path(__file__).parents[2]


def counts(path: Path) -> dict[str, int]:
    """Messages per topic, as rosbags (not our code) reads and decodes them."""
    seen: dict[str, int] = {}
    with AnyReader([path]) as reader:
        for connection, _, raw in reader.messages():
            reader.deserialize(raw, connection.msgtype)
            seen[connection.topic] = seen.get(connection.topic, 0) + 1
    return seen


def test_a_recorded_simulation_reads_back_with_every_topic(tmp_path):
    path = tmp_path / "run.mcap"
    done = subprocess.run([*PRIME, "sim", "--duration", "3", "--record", str(path), "--json"],  # in real time
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    seen = counts(path)
    ticks = summary["ticks"]
    dropped = summary["record"]["dropped_ticks"]  # counted, and flagged, if the machine starved the recorder
    assert seen["/prime/joint_states"] == ticks - dropped and seen["/prime/command"] == ticks - dropped
    assert dropped < ticks / 10
    assert seen["/control_mode"] == len(summary["modes_visited"])
    assert seen["/safety_status"] >= 1
    assert seen["/remote_policy_controller/command"] > 0  # the demonstration's stream
    assert summary["record"]["messages"] == seen
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        info = reader.get_summary()
    assert header.profile == "ros2"
    assert {s.encoding for s in info.schemas.values()} == {"ros2msg"}
    channels = {c.topic: c for c in info.channels.values()}
    assert {c.message_encoding for c in channels.values()} == {"cdr"}
    assert "durability: 1" in channels["/control_mode"].metadata["offered_qos_profiles"]  # latched
    assert "durability: 2" in channels["/prime/joint_states"].metadata["offered_qos_profiles"]
    assert {c.compression for c in info.chunk_indexes} == {"zstd"}
    # Which configuration the run used: in the file's metadata, and in /safety_status as rosbags reads it.
    with open(path, "rb") as f:
        metadata = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert metadata["prime_hardware"]["path"] == summary["config"]["hardware"]["path"]
    assert metadata["prime_controllers"]["sha256"] == summary["config"]["controllers"]["sha256"]
    with AnyReader([path]) as reader:
        statuses = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                    if c.topic == "/safety_status"]
    configuration = next(s for s in statuses[0].status if s.name == "prime/configuration")
    values = {v.key: v.value for v in configuration.values}
    assert values["controllers_sha256"] == summary["config"]["controllers"]["sha256"]
    assert values["hardware"] == summary["config"]["hardware"]["path"]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_recording_stopped_by_a_signal_mid_run_is_readable(tmp_path, sig):
    path = tmp_path / "run.mcap"
    summary = tmp_path / "summary.json"
    process = popen([*PRIME, "sim", "--duration", "120", "--record", str(path), "--summary", str(summary)],
                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for line in process.stdout:  # wait for a progress line that shows the loop ticking
            words = line.split()
            if "ticks" in words and int(words[words.index("ticks") + 1]) >= 50:
                break
        process.send_signal(sig)
        process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    seen = counts(path)
    run = json.loads(summary.read_text())
    assert run["ticks"] > 0 and seen["/prime/joint_states"] == run["ticks"] - run["record"]["dropped_ticks"]


def test_the_bundled_message_definition_is_the_interface_packages():
    assert bundled("prime_msgs/MitCommand.msg").read_bytes() == \
        (REPOSITORY / "prime_msgs" / "msg" / "MitCommand.msg").read_bytes()


def test_prime_plot_draws_a_recording_and_refuses_what_is_not_one(tmp_path):
    path = tmp_path / "run.mcap"
    subprocess.run([*PRIME, "sim", "--fast", "--duration", "2", "--record", str(path)], check=True,
                   capture_output=True, timeout=300)
    done = subprocess.run([*PRIME, "plot", str(path), "left_elbow_pitch", "right_wrist_pitch"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert path.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (tmp_path / "bad.mcap").write_text("not a recording")
    for args, says in (([str(tmp_path / "bad.mcap")], "is not a readable MCAP recording"),
                       ([str(path), "left_knee"], "no joint 'left_knee' in the recording"),
                       ([str(tmp_path / "none.mcap")], "No such file or directory")):
        done = subprocess.run([*PRIME, "plot", *args], capture_output=True, text=True, timeout=120)
        assert done.returncode == 1 and says in done.stderr and len(done.stderr.splitlines()) == 1, done.stderr


def test_record_refuses_a_file_that_is_not_mcap(tmp_path):
    done = subprocess.run([*PRIME, "sim", "--record", str(tmp_path / "run.bag")], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2 and "a recording is an .mcap file" in done.stderr


def test_the_recording_benchmark_records_every_tick_at_both_rates():
    from humanoid_prime.bench.dds import bench_record

    results = bench_record(seconds=0.5)
    for rate in ("50_hz", "1000_hz"):
        recorded = results[rate]["with"]
        assert recorded["recorder"]["messages"]["/prime/joint_states"] + recorded["recorder"]["dropped_ticks"] == \
            recorded["ticks"]
        # the figure: the recorder attached and detached in turns of one run, so it recorded only some ticks
        paired = results[rate]["paired"]
        assert 0 < paired["recorder"]["messages"]["/prime/joint_states"] < paired["ticks"]
        assert results[rate]["added_tick_us_median"] == paired["paired_us"]["added"]


def test_a_simulation_as_fast_as_it_goes_records_every_tick(tmp_path):
    """--fast has no real-time deadline: the loop waits for the writer instead of dropping a tick."""
    path = tmp_path / "fast.mcap"
    done = subprocess.run([*PRIME, "sim", "--fast", "--duration", "10", "--record", str(path), "--json"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["record"]["dropped_ticks"] == 0
    seen = counts(path)
    assert seen["/prime/joint_states"] == summary["ticks"] == 2000
    # What Foxglove's 3D panel and `ros2 bag play` need: /tf and /clock every tick, the description and the
    # fixed frames once, /diagnostics on change and every simulated second.
    assert seen["/tf"] == seen["/clock"] == 2000
    assert seen["/robot_description"] == seen["/tf_static"] == 1
    assert 10 <= seen["/diagnostics"] <= 10 + seen["/safety_status"]


def test_a_recording_holds_the_robot_for_a_3d_view(tmp_path, sim_robot):
    path = tmp_path / "small.mcap"
    done = subprocess.run([*PRIME, "sim", "--fast", "--duration", "1", "--record", str(path), "--topics",
                           "/tf,tf_static,/robot_description", "--json"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    with AnyReader([path]) as reader:
        messages = [(c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]
    assert {topic for topic, _ in messages} == {"/tf", "/tf_static", "/robot_description"}
    description = next(m for topic, m in messages if topic == "/robot_description")
    assert description.data == sim_robot.description.urdf
    static = next(m for topic, m in messages if topic == "/tf_static")
    frames = {(t.header.frame_id, t.child_frame_id) for _, m in messages if _ == "/tf" for t in m.transforms}
    links = frames | {(t.header.frame_id, t.child_frame_id) for t in static.transforms}
    assert {child for _, child in links} >= {"left_hand_link", "right_hand_link", "torso_link"}
    stamps = [m.transforms[0].header.stamp for topic, m in messages if topic == "/tf"]
    assert len(stamps) == json.loads(done.stdout)["ticks"] and stamps[-1].sec * 10**9 + stamps[-1].nanosec > 0


@pytest.mark.parametrize(("args", "status", "says"), [
    (["--topics", "/tf"], 1, "--topics needs --record"),
    (["--record", "x.mcap", "--topics", "/tf,/odom"], 2, "/odom: a recording can hold /prime/joint_states"),
])
def test_topics_is_checked_before_anything_starts(tmp_path, args, status, says):
    done = subprocess.run([*PRIME, "sim", "--fast", "--duration", "1", *args], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path)
    assert done.returncode == status and says in done.stderr, done.stderr
    assert not (tmp_path / "x.mcap").exists()
