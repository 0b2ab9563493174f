"""Bad files a command reads besides its configuration: recordings for `prime plot` and `prime replay` (empty,
cut short, garbage, another kind of file, a folder, missing) and the virtual robot's truth file for --emulate
(corrupt, or a calibration of some other wiring). Each is refused with one line naming the file, before anything
starts (before a view serves, before the emulator's private network namespace)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from cli.bad_input.harness import check
from humanoid_prime.files import bundled


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A short real recording, made once (the only run this suite starts)."""
    folder = tmp_path_factory.mktemp("rec")
    path = folder / "good.mcap"
    subprocess.run([sys.executable, "-m", "humanoid_prime", "sim", "--fast", "--duration", "0.3", "--record",
                    str(path), "--socket", str(folder / "c.sock")], check=True, capture_output=True, timeout=300)
    return path.read_bytes()


def _cut(fraction: float):
    return lambda good: good[:int(len(good) * fraction)]


RECORDINGS = {  # what the file holds -> how to make it from a good recording (None: a folder; ...: missing)
    "empty": lambda good: b"",
    "the magic only": lambda good: good[:8],
    "cut at 10%": _cut(0.1),
    "cut at 50%": _cut(0.5),
    "cut at 95%": _cut(0.95),
    "garbage": lambda good: bytes(range(256)) * 16,
    "a YAML file": lambda good: bundled("prime_hardware.yaml").read_bytes(),
    "a PNG": lambda good: b"\x89PNG\r\n\x1a\n" + b"\x00" * 64,
    "a folder": None,
    "missing": ...,
}
READERS = {"plot": ["plot", "{file}", "--output", "{tmp}/out.png"], "replay": ["replay", "{file}", "--no-wait"]}


@pytest.mark.parametrize("reader", READERS)
@pytest.mark.parametrize("kind", RECORDINGS)
def test_a_recording_that_is_not_one_is_one_line_naming_it(folder, monkeypatch, recording, reader, kind):
    path = folder / "bad.mcap"
    make = RECORDINGS[kind]
    if make is None:
        path.mkdir()
    elif make is not ...:
        path.write_bytes(make(recording))
    argv = [a.replace("{file}", str(path)) for a in READERS[reader]]
    check(argv, folder, monkeypatch, needles=("bad.mcap",))
    assert not (folder / "out.png").exists()


TRUTHS = {  # a truth file -> what the line must say
    "empty": ("", "empty"),
    "garbage": ("\udcff\udcfe binary", "not UTF-8"),
    "a direction of 3": (bundled("prime_calibration.yaml").read_text().replace("direction: 1", "direction: 3", 1),
                         "direction"),
    "another wiring": (bundled("prime_calibration.yaml").read_text().replace("address: ring 0", "address: ring 7",
                                                                              1), "ring 7"),
}


@pytest.mark.parametrize("command", [["bringup", "--emulate"], ["calibrate", "--emulate", "--output", "{tmp}/c.yaml"]],
                         ids=["bringup", "calibrate"])
@pytest.mark.parametrize("kind", TRUTHS)
def test_a_bad_truth_file_is_refused_before_the_emulator_starts(folder, monkeypatch, command, kind):
    text, says = TRUTHS[kind]
    truth = folder / "truth.yaml"
    truth.write_bytes(text.encode("utf-8", "surrogateescape"))
    check([*command, "--truth", str(truth)], folder, monkeypatch, needles=("truth.yaml", says))
