"""The eRob calibration fold: per-slave configs whose factors/offsets carry the calibration (DESIGN §2, §5)."""

import math

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from humanoid_prime.calibration.math import calibrate_from_sweeps
from humanoid_prime.config.calibration import JointCalibration, identity_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.description import ETHERCAT_BLOCK
from humanoid_prime.drivers.erob.constants import PRODUCT_CODE, RATED_TORQUE_NM, VENDOR_ID
from humanoid_prime.drivers.erob.gains import following_window_counts, gains_to_registers
from humanoid_prime.drivers.erob.objects import RXPDO, TXPDO
from humanoid_prime.drivers.ethercat.fold import fold_slave_config, render_slave_config, write_folded_configs
from humanoid_prime.drivers.ethercat.slave_config import Channel, load_slave_config, parse_slave_config
from humanoid_prime.errors import ConfigError
from humanoid_prime.modes import Mode

C = 524288 / (2 * math.pi)


def load_slave_config_from_doc(doc):
    return parse_slave_config(doc, "test")


@pytest.fixture(scope="module")
def elbow(robot):
    return robot.joints[robot.index("left_elbow_pitch")]


@pytest.fixture
def folded(tmp_path, elbow):
    path = tmp_path / "left_elbow_pitch.yaml"
    path.write_text(render_slave_config(fold_slave_config(elbow, JointCalibration(-1, 0.25))))
    return load_slave_config(path)


def test_one_output_revolution_of_counts_reads_two_pi(elbow):
    folded = load_slave_config_from_doc(fold_slave_config(elbow, JointCalibration(1, 0.0)))
    assert folded.state("position").state_value(524288) == pytest.approx(2 * math.pi, abs=1e-12)
    assert folded.command("position").command_raw(2 * math.pi) == 524288


def test_identity_and_dc_sync0(elbow):
    doc = fold_slave_config(elbow, JointCalibration(1, 0.0))
    assert (doc["vendor_id"], doc["product_id"], doc["assign_activate"]) == (VENDOR_ID, PRODUCT_CODE, 0x0300)
    assert (doc["vendor_id"], doc["product_id"]) == (0x5A65726F, 0x00029252)


def test_channels_follow_the_pdo_layout_without_its_pad_byte(elbow):
    doc = fold_slave_config(elbow, JointCalibration(1, 0.0))
    assert doc["rpdo"][0]["index"] == 0x1600 and doc["tpdo"][0]["index"] == 0x1A00
    assert RXPDO[-1].index == TXPDO[-1].index == 0  # Prime's own mapping ends in a pad byte ...
    # ... which a gap channel would carry into ICube's position-indexed channel list: left out
    assert [c["index"] for c in doc["rpdo"][0]["channels"]] == [e.index for e in RXPDO[:-1]]
    assert [c["index"] for c in doc["tpdo"][0]["channels"]] == [e.index for e in TXPDO[:-1]]
    assert [c["type"] for c in doc["rpdo"][0]["channels"]] == ["uint16", "int32", "int32", "int16", "int8"]
    assert [c["type"] for c in doc["tpdo"][0]["channels"]] == ["uint16", "int32", "int32", "int16", "uint16", "int8"]


def test_mode_of_operation_defaults_to_csp(folded):
    assert folded.command("mode_of_operation").default == 8


def test_state_position_factor_and_offset(folded):
    channel = folded.state("position")
    assert (channel.index, channel.factor, channel.offset) == (0x6064, -1 / C, pytest.approx(0.25))


def test_command_position_factor_and_offset(folded):
    channel = folded.command("position")
    assert (channel.index, channel.factor, channel.offset) == (0x607A, -C, pytest.approx(0.25 * C))
    assert math.isnan(channel.default)


def test_velocity_factors_have_no_offset(folded):
    assert (folded.state("velocity").factor, folded.state("velocity").offset) == (-1 / C, 0.0)
    assert (folded.command("velocity").index, folded.command("velocity").factor) == (0x60B1, -C)
    assert folded.command("velocity").offset == 0.0


def test_effort_is_per_mille_of_rated_torque(folded):
    assert folded.state("effort").factor == pytest.approx(-RATED_TORQUE_NM / 1000)
    assert folded.command("effort").factor == pytest.approx(-1000 / RATED_TORQUE_NM)
    assert folded.command("effort").index == 0x60B2


def test_no_sync_manager_block_is_generated(elbow):
    # ethercat_driver_ros2's default sync managers are the same, and older yaml-cpp cannot read `pdo: ~`
    assert "sm" not in fold_slave_config(elbow, JointCalibration(1, 0.0))
    assert "sm:" not in render_slave_config(fold_slave_config(elbow, JointCalibration(1, 0.0)))


def test_a_drive_fault_latches_in_the_generated_config(folded):
    assert folded.auto_fault_reset is False


# ethercat_driver_ros2's keys and types for a start-up SDO (ec_sdo_manager.hpp): index as<uint16_t>,
# sub_index as<uint8_t>, type one of its buffer_write types, value as<int> (signed 32-bit).
ICUBE_SDO_KEYS = ["index", "sub_index", "type", "value"]
ICUBE_SDO_TYPES = {"uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64"}


def test_fold_with_controllers_lists_the_startup_sdos_icube_writes(robot, tmp_path):
    controllers = load_controllers(robot.names)
    write_folded_configs(robot, identity_calibration(robot.hardware), tmp_path, controllers)
    text = (tmp_path / "left_elbow_pitch.yaml").read_text()
    raw = yaml.safe_load(text)["sdo"]
    assert all(list(entry) == ICUBE_SDO_KEYS for entry in raw)
    assert all(entry["type"] in ICUBE_SDO_TYPES and -(1 << 31) <= entry["value"] < 1 << 31 for entry in raw)
    assert all(isinstance(entry["index"], int) and 0 <= entry["sub_index"] <= 0xFF for entry in raw)
    assert "index: 0x2383" in text  # hex, as yaml-cpp reads it (no leading zero: that would be octal)
    elbow = robot.joints[robot.index("left_elbow_pitch")]
    kp, kd = controllers.mode_gains()[Mode.STANDBY]
    regs = gains_to_registers(kp, kd, kt=robot.hardware.erob_kt[elbow.name], gear=robot.hardware.erob_gear[elbow.name],
                              efficiency=robot.hardware.torque_efficiency)
    window = following_window_counts(elbow.effort_limit, controllers.mode_gains())
    assert [(e["index"], e["sub_index"], e["type"], e["value"]) for e in raw] == [
        (0x6065, 0, "int32", window),  # first, so the standby stiffness cannot trip 0x8500
        (0x2381, 2, "uint16", 0),  # integral off
        (0x2382, 1, "uint16", regs.pos_reg),
        (0x2381, 1, "uint16", regs.vel_reg),
        (0x2383, 0, "uint32", 1),  # last: the drive takes the bus gains only once they are written
    ]
    loaded = load_slave_config(tmp_path / "left_elbow_pitch.yaml").sdo
    assert [(e.index, e.sub_index, e.data) for e in loaded][-1] == (0x2383, 0, b"\x01\x00\x00\x00")


def test_fold_without_controllers_has_no_sdo_list(robot, tmp_path):
    write_folded_configs(robot, identity_calibration(robot.hardware), tmp_path)
    assert "sdo" not in yaml.safe_load((tmp_path / "left_elbow_pitch.yaml").read_text())


def test_the_header_says_how_the_cpp_stack_differs(robot, tmp_path):
    write_folded_configs(robot, identity_calibration(robot.hardware), tmp_path)
    header = (tmp_path / "left_elbow_pitch.yaml").read_text().split("vendor_id")[0]
    assert "truncates" in header and "one count" in header
    assert "fault latches" in header


def test_rendered_text_reads_back_as_the_document(elbow):
    doc = fold_slave_config(elbow, JointCalibration(-1, 0.123456789))
    loaded = yaml.safe_load(render_slave_config(doc))
    doc["rpdo"][0]["channels"][1]["default"] = loaded["rpdo"][0]["channels"][1]["default"] = "nan"
    assert loaded == doc


def test_sito_joint_has_no_slave_config(robot):
    with pytest.raises(ValueError, match="Sito"):
        fold_slave_config(robot.joints[robot.index("left_wrist_roll")], JointCalibration())


def test_write_folded_configs_names_the_files_the_description_references(robot, tmp_path):
    paths = write_folded_configs(robot, identity_calibration(robot.hardware), tmp_path)
    block = robot.description.block(ETHERCAT_BLOCK)
    referenced = {block.joint_params[j]["slave_config"].rsplit("/", 1)[-1] for j in block.joints}
    assert {p.name for p in paths} == referenced
    assert len(paths) == 10


def test_folded_config_reads_the_limit_at_each_stop(robot, tmp_path):
    """Sweep each eRob joint of a simulated robot, calibrate, fold: the stops read the URDF limits."""
    true = {j.name: JointCalibration(-1 if j.index % 2 else 1, 0.37 - 0.11 * j.index) for j in robot.joints}
    sweeps = {}
    for j in robot.joints:
        d, off = true[j.name].direction, true[j.name].homing_offset
        raw_at_stops = [d * q + off for q in (j.lower, j.upper)]
        sweeps[j.name] = (min(d * r for r in raw_at_stops), max(d * r for r in raw_at_stops))
    prior = identity_calibration(robot.hardware, {n: c.direction for n, c in true.items()})
    calibration, _ = calibrate_from_sweeps(sweeps, prior, robot)
    write_folded_configs(robot, calibration, tmp_path)
    for j in robot.joints:
        if j.family != "erob":
            continue
        position = load_slave_config(tmp_path / f"{j.name}.yaml").state("position")
        d, off = true[j.name].direction, true[j.name].homing_offset
        for limit in (j.lower, j.upper):
            counts = round((d * limit + off) * C)  # what the output encoder reports at that stop
            assert position.state_value(counts) == pytest.approx(limit, abs=1 / C)


def test_default_target_is_the_actual_position(folded):
    """The C++ driver holds CSP at command_factor * state + command_offset: that must be the raw position."""
    raw = 123456
    command = folded.command("position")
    held = command.factor * folded.state("position").state_value(raw) + command.offset
    assert held == pytest.approx(raw, abs=1e-6)


calibrations = st.builds(JointCalibration, st.sampled_from([1, -1]), st.floats(-math.pi, math.pi))


@given(cal=calibrations, q=st.floats(-3.2, 3.2))
def test_position_command_then_state_returns_the_joint_value(elbow, cal, q):
    doc = fold_slave_config(elbow, cal)
    command = _channel(doc, "rpdo", "position")
    state = _channel(doc, "tpdo", "position")
    assert state.state_value(command.command_raw(q)) == pytest.approx(q, abs=0.5 / C + 1e-12)
    assert state.state_value(state.unfold_state(q)) == pytest.approx(q, abs=1e-12)
    assert command.unfold_command(command.factor * q + command.offset) == pytest.approx(q, abs=1e-9)


@given(cal=calibrations, qd=st.floats(-20.0, 20.0), tau=st.floats(-30.0, 30.0))
def test_velocity_and_effort_command_then_state_return_the_value(elbow, cal, qd, tau):
    doc = fold_slave_config(elbow, cal)
    velocity = _channel(doc, "tpdo", "velocity").state_value(_channel(doc, "rpdo", "velocity").command_raw(qd))
    effort = _channel(doc, "tpdo", "effort").state_value(_channel(doc, "rpdo", "effort").command_raw(tau))
    assert velocity == pytest.approx(qd, abs=0.5 / C + 1e-12)
    assert effort == pytest.approx(tau, abs=0.5 * RATED_TORQUE_NM / 1000 + 1e-12)


def _channel(doc, section, interface):
    key = "command_interface" if section == "rpdo" else "state_interface"
    raw = next(c for c in doc[section][0]["channels"] if c.get(key) == interface)
    return Channel(raw["index"], raw["sub_index"], raw["type"], interface, raw["factor"], raw["offset"])


# slave config loader ----------------------------------------------------------------------------------------

def test_command_raw_clamps_to_the_type(folded):
    assert folded.command("effort").command_raw(1e6) == -32768  # direction -1
    assert folded.command("effort").command_raw(-1e6) == 32767


def test_command_raw_refuses_non_finite(folded):
    with pytest.raises(ValueError, match="not finite"):
        folded.command("position").command_raw(math.nan)


def _write(tmp_path, elbow, edit):
    doc = fold_slave_config(elbow, JointCalibration(1, 0.0))
    edit(doc)
    path = tmp_path / "slave.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


@pytest.mark.parametrize("edit, key, problem", [
    (lambda d: d.pop("vendor_id"), "vendor_id", "expected an integer"),
    (lambda d: d.update(auto_fault_reset="yes please"), "auto_fault_reset", "true or false"),
    (lambda d: d["rpdo"][0]["channels"][1].update(type="float32"), "rpdo[0].channels[1].type", "unknown type"),
    (lambda d: d["tpdo"][0]["channels"][1].update(factor=0.0), "tpdo[0].channels[1].factor", "must not be 0"),
    (lambda d: d["tpdo"][0]["channels"][1].update(offset=math.inf), "tpdo[0].channels[1].offset", "finite"),
    (lambda d: d["rpdo"][0]["channels"][2].update(command_interface="position"),
     "rpdo[0].channels[2].command_interface", "already mapped"),
    (lambda d: d["rpdo"][0]["channels"][1].update(state_interface="position"),
     "rpdo[0].channels[1].state_interface", "not allowed here"),
    (lambda d: d["tpdo"][0].update(channels=[]), "tpdo[0].channels", "missing or empty"),
    (lambda d: d.update(sm=[{"index": 2, "type": "sideways"}]), "sm[0].type", "expected one of"),
    (lambda d: d.update(sdo=[{"index": 0x2383, "sub_index": 0, "type": "uint32"}]), "sdo[0].value", "missing"),
    (lambda d: d.update(sdo=[{"index": 0x2383, "sub_index": 0, "type": "uint32", "value": 0x80000000}]),
     "sdo[0].value", "0x0..0x7FFFFFFF"),
    (lambda d: d.update(sdo=[{"index": 0x2383, "sub_index": 0, "type": "bool", "value": 1}]), "sdo[0].type",
     "unknown type"),
    (lambda d: d.update(sdo=[{"index": 0x6065, "sub_index": 0, "type": "int16", "value": -40000}]),
     "sdo[0].value", "-32768..32767"),
    (lambda d: d["rpdo"][0]["channels"][0].update(index=0x10000), "rpdo[0].channels[0].index", "0x0..0xFFFF"),
])
def test_malformed_slave_config_names_file_and_key(tmp_path, elbow, edit, key, problem):
    path = _write(tmp_path, elbow, edit)
    with pytest.raises(ConfigError) as info:
        load_slave_config(path)
    assert (info.value.file, info.value.key) == (str(path), key)
    assert problem in str(info.value) and str(path) in str(info.value)


def test_missing_interface_names_the_file(tmp_path, elbow):
    path = _write(tmp_path, elbow, lambda d: d["tpdo"][0]["channels"][3].update(state_interface=None))
    with pytest.raises(ConfigError, match="no channel with state_interface: effort") as info:
        load_slave_config(path).state("effort")
    assert info.value.file == str(path)
