"""The emulator process: a raw AF_PACKET socket on one interface (EtherType 0x88A4 only), each frame
passed through the ring and sent back at once, the plant advanced between frames, and the control
channel served in the same loop. (Over 450 lines: that one loop and the slowness it plays, below, share its timing
state, which would cross a module boundary on every frame.)

SOEM waits 2 ms for a frame before it gives up on it (EC_TIMEOUTRET), so the loop keeps pauses short:
the garbage collector is frozen after start-up and disabled while serving (generation-0 collections run
only when the ring has been idle for a while), the reply is sent before the plant is advanced, and a plant
that fell behind catches up one physics step between two looks at the sockets.

Slowness on purpose, as a busy host or a slow drive shows it to a master: frames held back (``delay``), a reply
frame that comes back after the master gave up on it (``hold_reply_frames``: the frames that take a mailbox
reply out of a slave), and stalls in which nothing is answered and every frame waits (``stall``, and at random
with ``stall_interval_s``). Slow mailbox replies are the ring's ``MailboxLatency``.
"""

from __future__ import annotations

import contextlib
import fcntl
import gc
import json
import os
import random
import select
import signal
import socket
import struct
import time
from array import array
from collections.abc import Callable
from typing import TypedDict, Unpack

from humanoid_prime.drivers.erob.objects import IDENTITY
from humanoid_prime.drivers.ethercat.wire import ETHERTYPE, SII_IDENTITY, Command
from humanoid_prime.virtual.ring.firmware import ErobFirmware
from humanoid_prime.virtual.ring.frames import Datagram, build_frame
from humanoid_prime.virtual.ring.options import RingSettings
from humanoid_prime.virtual.ring.ring import Ring
from humanoid_prime.virtual.ring.status import SlaveStatus, describe_slave

_TURNAROUND_SAMPLES = 65536
_IDLE_GC_NS = 200_000_000  # collect generation 0 only after this long without a frame
# Physics steps between two looks at the sockets: behind real time (a stalled host), the plant catches up one
# step at a time and a frame waiting meanwhile is answered after at most one step, not after all of them.
_STEPS_PER_LOOK = 1


class SdoLogEntry(TypedDict):
    """An SDO download a slave executed (the control channel's ``sdo_log``)."""

    seq: int
    time: float  # monotonic s
    position: int
    index: int
    sub: int
    value: int
    applied: bool  # False: a gain write the drive ignored, its gate 0x2383 being 0


class RingStats(TypedDict):
    """Frame counters and the responder's turnaround (the control channel's ``stats``)."""

    frames: int
    malformed: int
    stalls: int
    held_reply_frames: int
    slow_replies: int
    replies_timed: int
    turnaround_median_us: float | None  # None: no reply timed yet
    turnaround_p99_us: float | None
    turnaround_max_us: float | None


class EmulatorServer:
    """Serves ``ring`` on ``interface`` and the control channel on the UNIX socket ``control_path``."""

    def __init__(self, ring: Ring, interface: str, control_path: str,
                 clock: Callable[[], int] = time.monotonic_ns, parent_fd: int | None = None) -> None:
        self.ring = ring
        self.parent_fd = parent_fd
        self.interface = interface
        self.control_path = control_path
        self.clock = clock
        self.running = False
        self._drop_requests = 0
        self._drop_replies = 0
        self._delay_ns = 0
        self._delay_count = 0
        self._garbage = 0
        self._hold_replies: tuple[int, int, int | None] = (0, 0, None)  # (frames left, delay ns, ring position)
        self._stall_ns = 0  # a stall asked for over the control channel, to begin at the next look
        self._next_stall_ns = 0  # when the next random stall begins (0: none)
        self.stalls = 0
        self.held_reply_frames = 0
        self._delayed: list[tuple[int, bytes]] = []
        self._turnaround_ns = array("q", bytes(8 * _TURNAROUND_SAMPLES))
        self._turnaround_count = 0
        self._last_frame_ns = 0
        self._last_gc_ns = 0
        self._random = random.Random(0x88A4)
        self._raw = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0)  # EtherCAT once bound: this ring's only
        self._raw.bind((interface, ETHERTYPE))
        self._raw.setblocking(False)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(control_path)
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(control_path)
        self._listener.listen(8)
        self._listener.setblocking(False)
        self._clients: dict[int, tuple[socket.socket, bytearray]] = {}

    def close(self) -> None:
        for client, _buffer in self._clients.values():
            client.close()
        self._clients.clear()
        self._listener.close()
        self._raw.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.control_path)

    # ---- main loop ---------------------------------------------------------------------------------------
    def serve_forever(self) -> None:
        poller = select.poll()
        poller.register(self._raw.fileno(), select.POLLIN)
        poller.register(self._listener.fileno(), select.POLLIN)
        raw_fd = self._raw.fileno()
        listener_fd = self._listener.fileno()
        if self.parent_fd is not None:
            poller.register(self.parent_fd, select.POLLIN)
        buffer = bytearray(2048)
        view = memoryview(buffer)
        ring = self.ring
        gc.collect()
        gc.freeze()
        gc.disable()
        self.running = True
        caught_up = True
        ring.serve_waiting = lambda: self._serve_frames(buffer, view)
        self._schedule_stall(self.clock())
        try:
            while self.running:
                self._stall_if_due()
                timeout_ms = 1
                if not caught_up or (self._delayed and min(t for t, _frame in self._delayed) <= self.clock()):
                    timeout_ms = 0
                for fd, _event in poller.poll(timeout_ms):
                    if fd == raw_fd:
                        self._serve_frames(buffer, view)
                    elif fd == listener_fd:
                        self._accept(poller)
                    elif fd == self.parent_fd:
                        self.running = bool(os.read(fd, 64))  # end of file: the parent process is gone
                    else:
                        self._serve_client(fd, poller)
                now = self.clock()
                if self._delayed:
                    self._send_due(now)
                caught_up = ring.advance(now, max_steps=_STEPS_PER_LOOK)
                if now - self._last_frame_ns > _IDLE_GC_NS and now - self._last_gc_ns > _IDLE_GC_NS:
                    gc.collect(0)
                    self._last_gc_ns = now
        finally:
            ring.serve_waiting = None
            gc.enable()
            gc.unfreeze()

    def _schedule_stall(self, now: int) -> None:
        interval = self.ring.options.stall_interval_s
        self._next_stall_ns = now + round(self._random.expovariate(1.0 / interval) * 1e9) if interval else 0

    def _stall_if_due(self) -> None:
        """Answer nothing for a while (frames queue in the socket), as a process the host did not schedule."""
        if self._stall_ns:
            seconds, self._stall_ns = self._stall_ns / 1e9, 0
        elif self._next_stall_ns and self.clock() >= self._next_stall_ns:
            seconds = self.ring.options.stall_s
        else:
            return
        time.sleep(seconds)
        self.stalls += 1
        self._schedule_stall(self.clock())

    def _takes_reply(self) -> list[int] | None:
        """Replies taken so far by the slaves a reply-frame hold watches; None when no hold is armed."""
        left, _delay, position = self._hold_replies
        if not left:
            return None
        slaves = self.ring.slaves if position is None else [self.ring.slaves[position]]
        return [slave.replies_taken for slave in slaves]

    def _serve_frames(self, buffer: bytearray, view: memoryview) -> None:
        raw = self._raw
        ring = self.ring
        clock = self.clock
        while True:
            try:
                size = raw.recv_into(buffer)
            except BlockingIOError:
                return
            start = clock()
            self._last_frame_ns = start
            if self._drop_requests:
                self._drop_requests -= 1
                continue
            frame = bytearray(view[:size])
            taken = self._takes_reply()
            if not ring.process(frame, start):
                continue
            frame[6] |= 0x02  # the first ESC marks the source MAC as locally administered
            if self._drop_replies:
                self._drop_replies -= 1
                continue
            if self._garbage:
                self._garbage -= 1
                self._send_garbage()
            if taken is not None and taken != self._takes_reply():  # this frame took a mailbox reply out
                left, delay_ns, position = self._hold_replies
                self._hold_replies = (left - 1, delay_ns, position)
                self.held_reply_frames += 1
                self._delayed.append((start + delay_ns, bytes(frame)))
                continue
            if self._delay_count:
                self._delay_count -= 1
                self._delayed.append((start + self._delay_ns, bytes(frame)))
                continue
            raw.send(frame)
            self._turnaround_ns[self._turnaround_count % _TURNAROUND_SAMPLES] = clock() - start
            self._turnaround_count += 1

    def _send_due(self, now: int) -> None:
        due = [f for t, f in self._delayed if t <= now]
        self._delayed = [(t, f) for t, f in self._delayed if t > now]
        for frame in due:
            self._raw.send(frame)

    def _send_garbage(self) -> None:
        payload = bytes(self._random.getrandbits(8) for _ in range(self._random.randrange(2, 40)))
        # indices 0x80-0xFF: outside the 16 frame buffers SOEM cycles through, so a correct master drops them
        datagram = Datagram(Command(self._random.randrange(1, 15)), payload, index=self._random.randrange(0x80, 0x100),
                            adp=self._random.getrandbits(16), ado=self._random.getrandbits(16))
        self._raw.send(build_frame([datagram], source=b"\x03\x01\x01\x01\x01\x01"))

    # ---- control channel ----------------------------------------------------------------------------------
    def _accept(self, poller: select.poll) -> None:
        try:
            client, _address = self._listener.accept()
        except BlockingIOError:
            return
        client.setblocking(False)
        self._clients[client.fileno()] = (client, bytearray())
        poller.register(client.fileno(), select.POLLIN)

    def _serve_client(self, fd: int, poller: select.poll) -> None:
        client, pending = self._clients[fd]
        try:
            data = client.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            poller.unregister(fd)
            client.close()
            del self._clients[fd]
            return
        pending += data
        while b"\n" in pending:
            line, _, rest = pending.partition(b"\n")
            pending[:] = rest
            reply = self._dispatch(line)
            client.setblocking(True)
            try:
                client.sendall(json.dumps(reply).encode() + b"\n")
            except OSError:
                pass
            finally:
                client.setblocking(False)

    def _dispatch(self, line: bytes | bytearray) -> dict[str, object]:
        try:
            request = json.loads(line)
            if not isinstance(request, dict):
                return {"ok": False, "error": f"a request is a JSON object, got {line.decode(errors='replace')!r}"}
            op = request.pop("op")
            handler = getattr(self, f"_op_{op}", None)
            if handler is None:
                return {"ok": False, "error": f"unknown operation {op!r}"}
            return {"ok": True, "result": handler(**request)}
        except (TypeError, ValueError, KeyError, IndexError) as exc:
            return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}

    def _slave(self, position: int) -> ErobFirmware:
        if not 0 <= position < len(self.ring.slaves):
            raise IndexError(f"no slave at ring position {position} (ring has {len(self.ring.slaves)})")
        return self.ring.slaves[position]

    def _op_ping(self) -> str:
        return "pong"

    def _op_status(self, position: int | None = None) -> list[SlaveStatus]:
        positions = range(len(self.ring.slaves)) if position is None else [self._slave(position).position]
        now = self.clock()
        return [describe_slave(self.ring, p, now) for p in positions]

    def _op_sdo_log(self, since: int = 0) -> list[SdoLogEntry]:
        return [{"seq": since + i, "time": t, "position": p, "index": index, "sub": sub, "value": value,
                 "applied": applied}
                for i, (t, p, index, sub, value, applied) in enumerate(self.ring.sdo_log[since:])]

    def _op_stats(self) -> RingStats:
        count = min(self._turnaround_count, _TURNAROUND_SAMPLES)
        samples = sorted(self._turnaround_ns[:count])
        def percentile(p: float) -> float | None:
            return samples[min(count - 1, int(p * count))] / 1000.0 if count else None
        return {"frames": self.ring.frames, "malformed": self.ring.dropped_malformed, "stalls": self.stalls,
                "held_reply_frames": self.held_reply_frames, "slow_replies": self.ring.latency.slowed,
                "replies_timed": self._turnaround_count, "turnaround_median_us": percentile(0.5),
                "turnaround_p99_us": percentile(0.99), "turnaround_max_us": samples[-1] / 1000.0 if count else None}

    def _op_set_external_torque(self, position: int, torque_nm: float) -> None:
        self.ring.plant.external[self._slave(position).position] = float(torque_nm)

    def _op_set_joint(self, position: int, q_rad: float, qd_rad_s: float = 0.0) -> None:
        position = self._slave(position).position
        self.ring.plant.q[position] = float(q_rad)
        self.ring.plant.qd[position] = float(qd_rad_s)

    def _op_drop(self, count: int, where: str = "request") -> None:
        if where == "request":
            self._drop_requests = int(count)
        elif where == "reply":
            self._drop_replies = int(count)
        else:
            raise ValueError(f"where must be 'request' or 'reply', got {where!r}")

    def _op_delay(self, seconds: float, count: int = 1) -> None:
        self._delay_ns = round(float(seconds) * 1e9)
        self._delay_count = int(count)

    def _op_late_replies(self, count: int, seconds: float, position: int | None = None) -> None:
        if position is not None:
            position = self._slave(position).position
        self.ring.latency.script(int(count), float(seconds), position)

    def _op_hold_reply_frames(self, count: int, seconds: float, position: int | None = None) -> None:
        if position is not None:
            position = self._slave(position).position
        if int(count) < 0 or not 0 <= float(seconds) < 10:
            raise ValueError(f"count must be >= 0 and seconds in [0, 10), got {count} and {seconds}")
        self._hold_replies = (int(count), round(float(seconds) * 1e9), position)

    def _op_stall(self, seconds: float) -> None:
        if not 0 < float(seconds) < 10:
            raise ValueError(f"a stall lasts more than 0 and less than 10 s, got {seconds}")
        self._stall_ns = round(float(seconds) * 1e9)

    def _op_garbage(self, count: int) -> None:
        self._garbage = int(count)

    def _op_lose(self, position: int) -> None:
        self.ring.lose(self._slave(position).position)

    def _op_restore(self, position: int) -> None:
        self.ring.restore(self._slave(position).position)

    def _op_silence(self, position: int, silent: bool = True) -> None:
        self._slave(position).set_silent(bool(silent))

    def _op_identity(self, position: int, product_code: int | None = None, revision: int | None = None) -> None:
        """From the next ring scan on, present another product code or revision (SII and 0x1018), as a drive of
        another model or firmware does."""
        slave = self._slave(position)
        _, product_word, revision_word = SII_IDENTITY
        for word, sub, value in ((product_word, 2, product_code), (revision_word, 3, revision)):
            if value is not None:
                struct.pack_into("<I", slave.esc.eeprom.image, 2 * word, int(value))
                slave.drive.od.set(IDENTITY, sub, int(value))

    def _op_fault(self, position: int, code: int, latched: bool = False) -> None:
        self._slave(position).drive.fault(int(code), latched=bool(latched))

    def _op_clear_latched(self, position: int) -> None:
        self._slave(position).drive.clear_latched()

    def _op_set_options(self, **options: Unpack[RingSettings]) -> None:
        allowed = {"dc_lock_cycles", "sync_tolerance", "sync_fault_cycles", "mailbox_latency_s", "state_change_s",
                   "mailbox_jitter_s", "mailbox_burst_s", "mailbox_burst_chance", "mailbox_burst_replies",
                   "stall_interval_s", "stall_s"}
        unknown = set(options) - allowed
        if unknown:
            raise ValueError(f"cannot change {sorted(unknown)} at run time; changeable: {sorted(allowed)}")
        previous = {name: getattr(self.ring.options, name) for name in options}
        for name, value in options.items():
            setattr(self.ring.options, name, type(getattr(self.ring.options, name))(value))
        try:
            self.ring.options.check()
        except ValueError:
            for name, value in previous.items():
                setattr(self.ring.options, name, value)
            raise
        if "stall_interval_s" in options:
            self._schedule_stall(self.clock())

    def _op_stop(self) -> None:
        self.running = False


REALTIME_PRIORITY = 20


def raise_to_realtime(priority: int) -> None:
    """``SCHED_FIFO`` at ``priority`` for the calling thread where permitted, unless it already runs at
    ``SCHED_FIFO`` that high (the virtual Prime asks for more, just below the control loop's)."""
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) == os.SCHED_FIFO and os.sched_getparam(0).sched_priority >= priority:
            return
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))


def run_until_signalled(server: EmulatorServer) -> None:
    """Serve until SIGTERM, SIGINT, a ``stop`` request or the parent's death, then close the server.

    Hardware answers at once, so the emulator asks for real-time scheduling (ignored where not permitted):
    an ordinary process that stalls it would look like lost frames to the master."""

    def stop(_signum: int, _frame: object) -> None:
        server.running = False

    raise_to_realtime(REALTIME_PRIORITY)
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        server.serve_forever()
    finally:
        server.close()


def disable_ipv6(interface: str) -> None:
    """Turn IPv6 off on ``interface`` so the kernel sends nothing of its own on an EtherCAT link."""
    with contextlib.suppress(OSError), open(f"/proc/sys/net/ipv6/conf/{interface}/disable_ipv6", "w") as f:
        f.write("1")


def bring_up(interface: str) -> None:
    """Set ``interface`` up with IPv6 off."""
    disable_ipv6(interface)
    siocgifflags, siocsifflags, iff_up = 0x8913, 0x8914, 0x1
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        request = struct.pack("16sH14x", interface.encode(), 0)
        flags = struct.unpack("16sH14x", fcntl.ioctl(s.fileno(), siocgifflags, request))[1]
        fcntl.ioctl(s.fileno(), siocsifflags, struct.pack("16sH14x", interface.encode(), flags | iff_up))
