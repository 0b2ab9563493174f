"""The CAN checks against the SocketCAN links ``ip -details -statistics -json`` reports (each state a real
controller shows), and the wrists heard, or not, on an emulated bus."""

from __future__ import annotations

from collections import Counter

import can
import pytest

from doubles.kernel import can_link, link
from doubles.sito import wait_until
from humanoid_prime.doctor import can as doctor_can
from humanoid_prime.doctor.report import Verdict
from humanoid_prime.drivers.sito.probe import Heard
from humanoid_prime.drivers.sito.protocol import MODE_MIT, Enable, FrameType, Gains, pack_frame
from humanoid_prime.virtual.plant import InertiaPlant
from humanoid_prime.virtual.sito import SitoEmulator


def by_name(checks):
    return {c.name: c for c in checks}


def test_a_healthy_link_passes_every_line():
    checks = doctor_can.link_checks("can2", 1_000_000, 4, True, can_link("can2"))
    assert [(c.name, c.verdict) for c in checks] == [(n, Verdict.PASS) for n in doctor_can.LINK_CHECKS]


@pytest.mark.parametrize(("state", "verdict"), [("ERROR-WARNING", Verdict.WARN), ("ERROR-PASSIVE", Verdict.FAIL),
                                                ("BUS-OFF", Verdict.FAIL), ("STOPPED", Verdict.FAIL)])
def test_a_controller_out_of_error_active_is_found_with_the_termination_to_check(state, verdict):
    check = by_name(doctor_can.link_checks("can2", 1_000_000, 4, True, can_link("can2", state=state)))["state"]
    assert check.verdict is verdict
    assert check.found.startswith(f"can2 is {state}")
    assert "120 ohm" in check.fix and "sudo ip link set can2 up" in check.fix


def test_a_wrong_bitrate_fails_with_the_command_that_sets_1_mbit():
    check = by_name(doctor_can.link_checks("can2", 1_000_000, 4, True, can_link("can2", bitrate=500_000)))["bitrate"]
    assert check.verdict is Verdict.FAIL
    assert check.found == "can2 runs at 500000 bit/s; the wrists and buses.can.bitrate say 1000000"
    assert check.fix == "sudo ip link set can2 down; sudo ip link set can2 up type can bitrate 1000000"


def test_a_link_that_is_down_fails_with_the_command_that_brings_it_up():
    check = by_name(doctor_can.link_checks("can2", 1_000_000, 4, True, can_link("can2", up=False)))["link"]
    assert check.verdict is Verdict.FAIL and check.fix.endswith("up type can bitrate 1000000")


def test_error_counters_warn_with_each_one_named():
    checks = doctor_can.link_checks("can2", 1_000_000, 4, True,
                                    can_link("can2", berr=(0, 135), xstats={"bus_off": 2, "restarts": 1}))
    check = by_name(checks)["errors"]
    assert check.verdict is Verdict.WARN
    assert check.found == "can2 counted errors: rx error counter 135, bus-off 2, restarts 1"


def test_the_default_queue_of_ten_frames_warns_with_the_command_that_lengthens_it():
    check = by_name(doctor_can.link_checks("can2", 1_000_000, 4, True, can_link("can2", txqlen=10)))["txqueuelen"]
    assert check.verdict is Verdict.WARN
    assert check.fix == "sudo ip link set can2 txqueuelen 1000"


def test_a_missing_interface_fails_and_the_rest_is_not_checked():
    checks = doctor_can.link_checks("can2", 1_000_000, 4, False, None)
    assert checks[0].verdict is Verdict.FAIL and "buses.can.channel" in checks[0].found
    assert all(not c.ran for c in checks[1:])


def test_a_vcan_has_no_bit_timing_and_no_state_and_says_so():
    vcan = link("vcan0", ["NOARP", "UP", "LOWER_UP"], operstate="UNKNOWN", txqlen=1000, link_type="can",
                linkinfo={"info_kind": "vcan"})
    checks = by_name(doctor_can.link_checks("vcan0", 1_000_000, 4, True, vcan))
    assert checks["link"].verdict is Verdict.PASS
    assert not checks["bitrate"].ran and "no bit timing" in checks["bitrate"].found
    assert not checks["state"].ran


def test_an_ethernet_link_named_as_the_can_channel_fails():
    check = doctor_can.link_checks("eth1", 1_000_000, 4, True, link("eth1", ["UP"], link_type="ether"))[0]
    assert check.verdict is Verdict.FAIL and check.found == "eth1 is a ether link, not CAN"


def test_wrists_unheard_without_a_probe_are_not_checked_and_name_the_probe():
    checks = doctor_can.wrist_checks({"left_wrist_roll": 22}, Heard(), probed=False, seconds=0.5)
    assert not checks[0].ran
    assert "a Sito sends only once enabled" in checks[0].found and checks[0].fix.startswith("prime doctor --op")


def test_a_wrist_silent_to_the_probe_fails_and_others_heard_are_named():
    checks = doctor_can.wrist_checks({"left_wrist_roll": 22, "left_wrist_pitch": 23},
                                     Heard({22: Counter(feedback1=5, feedback2=5), 40: Counter(feedback2=1)}),
                                     probed=True, seconds=0.5)
    assert [(c.name, c.verdict) for c in checks] == [("wrist.left_wrist_roll", Verdict.PASS),
                                                      ("wrist.left_wrist_pitch", Verdict.FAIL),
                                                      ("wrist.others", Verdict.WARN)]
    assert "id 23 is silent" in checks[1].found and "--ids 1-255" in checks[1].fix


def test_a_wrist_heard_only_in_frames_the_protocol_refuses_fails_with_the_problem():
    checks = doctor_can.wrist_checks({"left_wrist_roll": 22}, Heard(invalid={22: (3, "3 data bytes, every Sito frame "
                                                                                  "has 8")}),
                                     probed=True, seconds=0.5)
    assert checks[0].verdict is Verdict.FAIL
    assert checks[0].found == ("id 22 sent 3 frames the Sito protocol refuses (3 data bytes, every Sito frame has 8) "
                               "and no valid feedback")


@pytest.fixture
def wrists(robot, channel):
    """The four emulated wrists on a python-can virtual bus of their own, stepping in the background."""
    bus = can.Bus(interface="virtual", channel=channel)
    emulator = SitoEmulator.for_robot(robot, bus, InertiaPlant.wrists(4))
    emulator.start()
    yield emulator
    emulator.stop()
    bus.shutdown()


def test_the_limp_probe_hears_every_wrist_and_disables_each_after(robot, channel, wrists):
    checks = doctor_can.can_checks(robot.hardware, interface="virtual", channel=channel, op=True, seconds=0.5)
    assert [c.verdict for c in checks if c.name.startswith("wrist.")] == [Verdict.PASS] * 4
    motors = wrists.motors.values()
    wait_until(lambda: all(m.received[FrameType.DISABLE] == 1 for m in motors), "every wrist disabled")
    assert not any(m.enabled for m in motors)
    assert all(m.received[FrameType.GAINS] == 1 and m.kp == 0.0 and m.kd == 0.0 for m in motors)  # limp all along
    link_line = checks[0]
    assert not link_line.ran and "not a SocketCAN link" in link_line.found


def test_a_silent_wrist_is_found_by_the_probe(robot, channel, wrists):
    wrists.motors[robot.hardware.mit_joints["left_wrist_pitch"]].silent = True
    checks = by_name(doctor_can.can_checks(robot.hardware, interface="virtual", channel=channel, op=True,
                                           seconds=0.5))
    assert checks["wrist.left_wrist_pitch"].verdict is Verdict.FAIL
    assert checks["wrist.left_wrist_roll"].verdict is Verdict.PASS


def test_without_op_nothing_is_sent_to_a_wrist(robot, channel, wrists):
    checks = doctor_can.can_checks(robot.hardware, interface="virtual", channel=channel, op=False, seconds=0.2)
    assert all(not c.ran for c in checks if c.name.startswith("wrist."))
    assert sum(sum(m.received.values()) for m in wrists.motors.values()) == 0


def test_wrists_that_already_stream_are_not_probed_for_the_probe_s_disable_would_stop_them(robot, channel, wrists):
    driver = can.Bus(interface="virtual", channel=channel)  # a program that drives the wrists
    try:
        for frame in (Gains(0.0, 0.0), Enable(MODE_MIT, (10, 10, 0))):
            ident, data = pack_frame(22, frame)
            driver.send(can.Message(arbitration_id=ident, is_extended_id=True, data=data))
        wait_until(lambda: wrists.motors[22].feedback_sent > 0, "id 22 streaming")
        checks = by_name(doctor_can.can_checks(robot.hardware, interface="virtual", channel=channel, op=True,
                                               seconds=0.3))
    finally:
        driver.shutdown()
    assert checks["wrist.left_wrist_roll"].verdict is Verdict.PASS
    assert "answered unprompted" in checks["wrist.left_wrist_roll"].found
    assert not checks["wrist.left_wrist_pitch"].ran and "not probed" in checks["wrist.left_wrist_pitch"].found
    assert wrists.motors[22].enabled and wrists.motors[22].received[FrameType.DISABLE] == 0
    assert all(sum(wrists.motors[i].received.values()) == 0 for i in (23, 38, 39))
