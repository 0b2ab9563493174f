"""Bad paths, for every output of every command: a folder, a path under a regular file, a file inside the installed
package, a place the system will not let anyone write or create a file in, an input of the same command, another
output of the same run; and the control socket: a regular file, a folder, a path too long for a UNIX socket,
nothing listening. Each is refused with one line before anything starts, and every file the paths named is as it
was."""

from __future__ import annotations

import subprocess

import pytest

from cli.bad_input.harness import check
from humanoid_prime.files import bundled

# Every output option, with what else the command needs to get there ({out}: the path under test).
OUTPUTS = {
    "sim --summary": ["sim", "--summary", "{out}"],
    "sim --record": ["sim", "--record", "{out}.mcap"],
    "bringup --summary": ["bringup", "--summary", "{out}"],
    "bringup --record": ["bringup", "--record", "{out}.mcap"],
    "bringup --erob-config-dir": ["bringup", "--erob-config-dir", "{out}"],
    "calibrate --output": ["calibrate", "--output", "{out}"],
    "calibrate --plot": ["calibrate", "--plot", "{out}"],
    "calibrate --record": ["calibrate", "--record", "{out}.mcap"],
    "calibrate --summary": ["calibrate", "--summary", "{out}"],
    "bench --output": ["bench", "--output", "{out}"],
    "bench soak --output": ["bench", "soak", "--output", "{out}"],
    "plot --output": ["plot", "{tmp}/run.mcap", "--output", "{out}"],
    "calibration fold --output": ["calibration", "fold", "--output", "{out}"],
    "remote --summary": ["remote", "--summary", "{out}"],
    "can monitor --summary": ["can", "monitor", "--summary", "{out}"],
    "can emulate --summary": ["can", "emulate", "--summary", "{out}"],
    "limp --summary": ["limp", "4", "--summary", "{out}"],
}
FOLDERS = {"bringup --erob-config-dir", "calibration fold --output"}
PLACES = {  # what the path is -> (the path, what the line must say)
    "a folder": ("{tmp}/afolder", "folder"),
    "under a regular file": ("{tmp}/keep.txt/x", "keep.txt"),
    "inside the package": (str(bundled("prime_hardware.yaml").parent / "x"), "installed package"),
    "where nobody may write": ("/proc/1/x", "/proc/1"),
    # root may write /proc by its permission bits, yet nothing can be created there: the write's temporary file
    # is tried before the run
    "where nothing can be created": ("/proc/x", "in /proc"),
    "under folders nothing can create": ("/proc/a/b/x", "in /proc"),
}


def _place_cases():
    cases = []
    for what, argv in OUTPUTS.items():
        for place, (path, says) in PLACES.items():
            if what in FOLDERS and place == "a folder":
                continue  # a folder is what it takes
            out = path + ("/keep.txt" if what in FOLDERS and place == "a folder" else "")
            cases.append(pytest.param([a.replace("{out}", out) for a in argv], says, id=f"{what} {place}"))
    return cases


INPUTS = {  # an input option of most commands, and a file it may name
    "--hardware": "{tmp}/hw.yaml", "--calibration": "{tmp}/cal.yaml", "--controllers": "{tmp}/ctl.yaml",
}
READS = {"sim": ("--hardware", "--controllers"), "bringup": ("--hardware", "--calibration", "--controllers"),
         "calibrate": ("--hardware", "--controllers"), "plot": ("--hardware",), "remote": ("--hardware",),
         "calibration": ("--hardware", "--calibration", "--controllers")}


def _same_as_input_cases():
    cases = []
    for what, argv in OUTPUTS.items():
        command = argv[0]
        for option in READS.get(command, ()):
            if what in FOLDERS or what.endswith("--record"):
                continue  # a folder, an .mcap: never a configuration file's name
            path = INPUTS[option]
            cases.append(pytest.param([*[a.replace("{out}", path) for a in argv], option, path], option,
                                      id=f"{what} is {option}"))
    cases += [
        pytest.param(["plot", "{tmp}/run.mcap", "--output", "{tmp}/run.mcap"], "recording", id="plot output is input"),
        pytest.param(["calibrate", "--summary", "{tmp}/cal.yaml", "--prior", "{tmp}/cal.yaml"], "--prior",
                     id="calibrate --summary is --prior"),
        pytest.param(["calibrate", "--plot", "{tmp}/cal.yaml", "--output", "{tmp}/cal.yaml"], "--output",
                     id="calibrate --plot is --output"),
        pytest.param(["sim", "--summary", "{tmp}/x.mcap", "--record", "{tmp}/x.mcap"], "--record",
                     id="sim --summary is --record"),
        pytest.param(["bringup", "--summary", "{tmp}/x.mcap", "--record", "{tmp}/x.mcap"], "--record",
                     id="bringup --summary is --record"),
        pytest.param(["calibrate", "--emulate", "--summary", "{tmp}/truth.yaml", "--truth", "{tmp}/truth.yaml"],
                     "--truth", id="calibrate --summary is --truth"),
    ]
    return cases


SERVERS = {"sim": ["sim"], "bringup": ["bringup"], "calibrate": ["calibrate"]}
CLIENTS = {"switch": ["switch", "DAMPING"], "reset": ["reset"], "view": ["view"], "limp": ["limp", "4"]}
LONG = "{tmp}/" + "s" * 120 + ".sock"


def _socket_cases():
    cases = []
    for what, argv in SERVERS.items():
        for place, path, says in (("a regular file", "{tmp}/keep.txt", "keep.txt"),
                                  ("a folder", "{tmp}/afolder", "afolder"),
                                  ("too long", LONG, "107"),
                                  ("under a regular file", "{tmp}/keep.txt/x.sock", "keep.txt")):
            cases.append(pytest.param([*argv, "--socket", path], says, id=f"{what} --socket {place}"))
    for what, argv in CLIENTS.items():
        for place, path, says in (("nothing there", "{tmp}/none.sock", "none.sock"),
                                  ("a regular file", "{tmp}/keep.txt", "keep.txt"),
                                  ("a folder", "{tmp}/afolder", "afolder")):
            cases.append(pytest.param([*argv, "--socket", path], says, id=f"{what} --socket {place}"))
    return cases


@pytest.fixture
def folder(folder):
    """The case folder with the paths these cases name besides its inputs."""
    tmp_path = folder
    (tmp_path / "afolder").mkdir()
    (tmp_path / "afolder.mcap").mkdir()
    (tmp_path / "afolder" / "keep.txt").write_bytes(b"kept\n")
    for name, file in (("hw.yaml", "prime_hardware.yaml"), ("ctl.yaml", "prime_controllers.yaml"),
                       ("truth.yaml", "prime_calibration.yaml")):
        (tmp_path / name).write_bytes(bundled(file).read_bytes())
    (tmp_path / "run.mcap").write_bytes(b"\x89MCAP0\r\n not a real one")
    return tmp_path


@pytest.mark.parametrize("argv, says", _place_cases())
def test_an_output_that_cannot_be_written_is_refused_before_anything_starts(folder, monkeypatch, argv, says):
    check(argv, folder, monkeypatch, needles=(says,))


@pytest.mark.parametrize("argv, says", _same_as_input_cases())
def test_an_output_that_is_an_input_or_another_output_is_refused(folder, monkeypatch, argv, says):
    check(argv, folder, monkeypatch, needles=(says,))


@pytest.mark.parametrize("argv, says", _socket_cases())
def test_a_control_socket_path_that_is_not_one_is_refused(folder, monkeypatch, argv, says):
    check(argv, folder, monkeypatch, needles=(says,))


@pytest.mark.parametrize("argv", [["calibrate"], ["calibrate", "--auto", "--sim"], ["calibrate", "--emulate"]],
                         ids=" ".join)
def test_a_calibration_whose_own_file_cannot_be_written_is_refused_before_it_moves_a_joint(folder, monkeypatch,
                                                                                            argv):
    # no --output: the result goes to the robot's own file, in a folder where nothing can be created
    monkeypatch.setenv("PRIME_CONFIG_DIR", "/proc")
    check(argv, folder, monkeypatch, needles=("the calibration", "in /proc", "--output"))


@pytest.fixture
def immutable(folder):
    """A folder of the case's whose files can be read and replaced by nobody, root included (chattr +i)."""
    place = folder / "immutable"
    place.mkdir()
    (place / "prime_hardware.yaml").write_bytes(bundled("prime_hardware.yaml").read_bytes())
    if subprocess.run(["chattr", "+i", str(place)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not available on this file system")
    yield place
    subprocess.run(["chattr", "-i", str(place)], check=True)


def test_apply_into_a_hardware_file_that_cannot_be_replaced_is_refused_before_it_moves_a_joint(folder, immutable,
                                                                                               monkeypatch):
    hardware = immutable / "prime_hardware.yaml"
    check(["calibrate", "--auto", "--sim", "--apply", "--hardware", str(hardware), "--output", "{tmp}/cal.yaml"],
          folder, monkeypatch, needles=("--apply's hardware file", f"in {immutable}"))
