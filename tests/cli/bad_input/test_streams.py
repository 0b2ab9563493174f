"""Bad input that arrives while a command runs: requests on the control socket, and frames on the wrists' CAN bus
(garbage, foreign datagrams). Each is answered or set aside; the server and the emulated wrists go on."""

from __future__ import annotations

import json
import random
import socket

import can
import pytest

from cli.bad_input.harness import TOTALS
from humanoid_prime.cli.can import describe
from humanoid_prime.config.robot import load_robot
from humanoid_prime.drivers.sito.protocol import sito_model
from humanoid_prime.runtime.socket import MAX_REQUEST_BYTES, ControlServer
from humanoid_prime.virtual.plant import InertiaPlant
from humanoid_prime.virtual.sito import SitoEmulator

REQUESTS = {  # what a peer sends -> what the error must say
    "not JSON": (b"garbage\n", "bad request"),
    "not UTF-8": (b"\xff\xfe\x00\n", "bad request"),
    "a list": (b"[1, 2]\n", "bad request"),
    "null": (b"null\n", "bad request"),
    "a number": (b"42\n", "bad request"),
    "no op": (b"{}\n", "bad request"),
    "an unknown op": (b'{"op": "dance"}\n', "unknown op"),
    "an op that is a list": (b'{"op": ["mode"]}\n', "unknown op"),
    "mode without a mode": (b'{"op": "mode"}\n', "bad request"),
    "an unknown mode": (b'{"op": "mode", "mode": "DANCE"}\n', "DANCE"),
    "a mode that is a number": (b'{"op": "mode", "mode": 3}\n', "3"),
    "wait nan": (b'{"op": "mode", "mode": "DAMPING", "wait": NaN}\n', "wait"),
    "wait -1": (b'{"op": "mode", "mode": "DAMPING", "wait": -1}\n', "wait"),
    "wait 1e308": (b'{"op": "mode", "mode": "DAMPING", "wait": 1e308}\n', "wait"),
    "wait a word": (b'{"op": "mode", "mode": "DAMPING", "wait": "soon"}\n', "soon"),
    "limp without a drive": (b'{"op": "limp", "position": "x", "limp": true}\n', "prime limp"),
    "sdo without a master": (b'{"op": "sdo_read", "position": -1, "index": 0, "sub_index": 0}\n', "EtherCAT"),
    "reset without hardware": (b'{"op": "reset"}\n', "latches faults"),
    "a request too long": (b"{" + b" " * (MAX_REQUEST_BYTES + 10), "at most"),
    "nested 60,000 deep": (b"[" * 60000 + b"\n", "nested too deep"),
    "an op nested 9,000 deep": (b'{"op": ' + b'{"a": ' * 9000 + b"1" + b"}" * 9001 + b"\n", "nested too deep"),
}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    path = tmp_path_factory.mktemp("sock") / "c.sock"
    modes = []
    with ControlServer(path=path, switch_mode=lambda mode, wait: modes.append(mode) or {"mode": mode.value},
                       state=lambda: {"mode": "DAMPING"}) as running:
        yield running, modes


def _ask(path, data: bytes) -> dict:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
        conn.settimeout(10.0)
        conn.connect(str(path))
        conn.sendall(data)
        conn.shutdown(socket.SHUT_WR)
        reply = b""
        while chunk := conn.recv(4096):
            reply += chunk
    return json.loads(reply)


@pytest.mark.parametrize("data, says", list(REQUESTS.values()), ids=list(REQUESTS))
def test_a_bad_request_on_the_control_socket_is_one_error_and_the_server_goes_on(server, data, says):
    running, modes = server
    reply = _ask(running.path, data)
    assert reply["ok"] is False and says in reply["error"] and "\n" not in reply["error"], reply
    assert _ask(running.path, b'{"op": "ping"}\n') == {"ok": True, "ready": True}
    assert modes == []  # nothing bad reached the robot
    TOTALS["correct refusal"] += 1


def _garbage_frames(count: int) -> list[can.Message]:
    rng = random.Random(35)
    frames = []
    for _ in range(count):
        extended = rng.random() < 0.8
        ident = rng.randrange(1 << 29) if extended else rng.randrange(1 << 11)
        if rng.random() < 0.5:  # a Sito id and a host frame type, with any payload
            ident = (rng.choice((22, 23, 38, 39, 7)) << 8) | rng.choice((0x01, 0x02, 0x03, 0x04, 0x05, 0xB1, 0xFF))
        frames.append(can.Message(arbitration_id=ident, is_extended_id=extended or ident >= 1 << 11,
                                  is_remote_frame=rng.random() < 0.05, is_error_frame=rng.random() < 0.05,
                                  data=bytes(rng.randrange(256) for _ in range(rng.randrange(9)))))
    return frames


class _GarbageBus(can.BusABC):
    """A bus that delivers given frames and, between them, datagrams that are no CAN frame (as udp_multicast
    raises for them)."""

    def __init__(self, frames: list[can.Message]) -> None:
        self.frames = list(frames)
        self.sent: list[can.Message] = []
        super().__init__(channel="garbage")

    def _recv_internal(self, timeout):
        if not self.frames:
            return None, False
        frame = self.frames.pop(0)
        if frame is None:
            raise can.CanOperationError("a datagram that is no CAN frame")
        return frame, False

    def send(self, msg, timeout=None) -> None:
        self.sent.append(msg)


GARBAGE = _garbage_frames(100)


def test_every_garbage_frame_is_described_in_one_line_by_can_monitor(robot):
    joints = {can_id: joint for joint, can_id in robot.hardware.mit_joints.items()}
    for frame in GARBAGE:
        text = describe(frame, sito_model("TA40-50"), joints)
        assert isinstance(text, str) and "\n" not in text
        TOTALS["correct refusal" if any(w in text for w in ("INVALID", "foreign", "error frame")) else
               "correct acceptance"] += 1


def test_emulated_wrists_set_aside_garbage_and_foreign_datagrams_and_still_answer(robot):
    frames: list = []
    for frame in GARBAGE:
        frames += [frame, None]  # each followed by a datagram that is no CAN frame
    bus = _GarbageBus(frames)
    emulator = SitoEmulator.for_robot(load_robot(), bus, InertiaPlant.wrists(len(robot.hardware.sito_joints)))
    emulator.step(0.5)  # every frame and datagram is read on the first tick
    assert emulator.foreign_received == len(GARBAGE)
    assert emulator.frames_received == len(GARBAGE)
    TOTALS["correct refusal"] += 1
