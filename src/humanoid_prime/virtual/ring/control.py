"""The emulator's control channel: newline-delimited JSON over a UNIX stream socket.

A request is ``{"op": NAME, ...arguments}``; the reply ``{"ok": true, "result": ...}`` or
``{"ok": false, "error": TEXT}``. ``RingControl`` is the client (thread-safe); the operations are its
methods. Times are CLOCK_MONOTONIC seconds, comparable with ``time.monotonic()`` in any process.
"""

from __future__ import annotations

import json
import socket
import threading
from typing import Any

from humanoid_prime.errors import PrimeError


class ControlError(PrimeError):
    """The emulator refused a control request or could not be reached."""


class RingControl:
    """Client of a running emulator's control socket."""

    def __init__(self, path: str, timeout_s: float = 5.0) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout_s)
        try:
            self._sock.connect(path)
        except OSError as exc:
            self._sock.close()
            raise ControlError(f"cannot reach the emulator control socket {path}: {exc}") from exc
        self._reader = self._sock.makefile("rb")

    def close(self) -> None:
        with self._lock:
            self._reader.close()
            self._sock.close()

    def __enter__(self) -> RingControl:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def call(self, op: str, **arguments: Any) -> Any:
        """Send one request and return its result; ControlError when the emulator refuses it."""
        request = json.dumps({"op": op, **arguments}).encode() + b"\n"
        with self._lock:
            try:
                self._sock.sendall(request)
                line = self._reader.readline()
            except OSError as exc:
                raise ControlError(f"emulator control request {op!r} failed: {exc}") from exc
        if not line:
            raise ControlError(f"the emulator closed the control channel during {op!r}")
        reply = json.loads(line)
        if not reply.get("ok"):
            raise ControlError(f"emulator refused {op!r}: {reply.get('error')}")
        return reply.get("result")

    # ---- inspection ---------------------------------------------------------------------------------------
    def ping(self) -> None:
        self.call("ping")

    def status(self) -> list[dict[str, Any]]:
        """One dict per slave in ring order: AL state and code, DC lock, drive state, registers, joint."""
        return self.call("status")

    def slave(self, position: int) -> dict[str, Any]:
        return self.call("status", position=position)[0]

    def sdo_log(self, since: int = 0) -> list[dict[str, Any]]:
        """SDO downloads the slaves executed, oldest first, from entry ``since`` on. Each entry: ``seq``,
        ``time`` (monotonic s), ``position``, ``index``, ``sub``, ``value``, ``applied`` (False for a gain
        write the drive ignored because its gate 0x2383 was 0)."""
        return self.call("sdo_log", since=since)

    def stats(self) -> dict[str, Any]:
        """Frame counters and the responder's receive-to-send turnaround (median/p99 in us)."""
        return self.call("stats")

    # ---- the mechanics ----------------------------------------------------------------------------------
    def set_external_torque(self, position: int, torque_nm: float) -> None:
        self.call("set_external_torque", position=position, torque_nm=torque_nm)

    def set_joint(self, position: int, q_rad: float, qd_rad_s: float = 0.0) -> None:
        self.call("set_joint", position=position, q_rad=q_rad, qd_rad_s=qd_rad_s)

    # ---- fault injection ----------------------------------------------------------------------------------
    def drop_frames(self, count: int, where: str = "request") -> None:
        """Lose the next ``count`` frames: before the slaves see them (``request``) or on the way back
        after they acted on them (``reply``)."""
        self.call("drop", count=count, where=where)

    def delay_frames(self, seconds: float, count: int = 1) -> None:
        """Hold the replies to the next ``count`` frames back by ``seconds``."""
        self.call("delay", seconds=seconds, count=count)

    def late_replies(self, count: int, seconds: float, position: int | None = None) -> None:
        """The next ``count`` mailbox replies (of ring ``position``, or of any slave) come ``seconds`` later than
        the mailbox latency says: past a master's timeout, a reply that arrives after it gave up."""
        self.call("late_replies", count=count, seconds=seconds, position=position)

    def hold_reply_frames(self, count: int, seconds: float, position: int | None = None) -> None:
        """The next ``count`` frames that take a mailbox reply out of a slave (``position``, or any) come back
        ``seconds`` late: the slave has let the reply go, and the master sees it only after its frame timeout."""
        self.call("hold_reply_frames", count=count, seconds=seconds, position=position)

    def stall(self, seconds: float) -> None:
        """Answer no frame for ``seconds``, then every frame that waited (a host that did not schedule us)."""
        self.call("stall", seconds=seconds)

    def garbage_frames(self, count: int) -> None:
        """Send a junk EtherCAT frame (random command and payload, index 0x80-0xFF) ahead of each of the next
        ``count`` replies."""
        self.call("garbage", count=count)

    def lose_slave(self, position: int) -> None:
        """Power the slave off: the line ends before it."""
        self.call("lose", position=position)

    def restore_slave(self, position: int) -> None:
        """Power the slave on again (INIT, station address 0, drive re-initialised)."""
        self.call("restore", position=position)

    def silence(self, position: int, silent: bool = True) -> None:
        """Freeze the slave's firmware: its registers still answer, but inputs stop updating, outputs,
        AL requests and mailbox requests are ignored."""
        self.call("silence", position=position, silent=silent)

    def set_identity(self, position: int, *, product_code: int | None = None, revision: int | None = None) -> None:
        """From the next ring scan on, the slave presents this product code or revision (another model, or
        another firmware)."""
        self.call("identity", position=position, product_code=product_code, revision=revision)

    def inject_fault(self, position: int, code: int, latched: bool = False) -> None:
        """Fault the drive with ``code`` (0x603F); a latched fault survives fault resets until cleared."""
        self.call("fault", position=position, code=code, latched=latched)

    def clear_latched(self, position: int) -> None:
        self.call("clear_latched", position=position)

    def set_options(self, **options: Any) -> None:
        """Change tunables at run time: dc_lock_cycles, sync_tolerance, sync_fault_cycles, state_change_s, the
        mailbox latency model (mailbox_latency_s, mailbox_jitter_s, mailbox_burst_*) and random stalls
        (stall_interval_s, stall_s)."""
        self.call("set_options", **options)

    def stop(self) -> None:
        """Ask the emulator to exit."""
        self.call("stop")
