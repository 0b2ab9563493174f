"""The control socket of a running ``prime sim``, ``prime bringup`` or ``prime calibrate``.

A second terminal uses it to switch modes (``prime switch MODE``) and, when the process owns an
EtherCAT master, to reach the drives' mailboxes (``prime limp``, ``prime ec sdo``): with SOEM the
master lives inside that process, so SDO from another process goes through here.

One JSON request per connection, one JSON answer: ``{"op": "mode", "mode": "STANDBY", "wait": 5.0}`` (answered
once the switch has an outcome, or at once without ``wait``), ``{"op": "reset"}``
(the operator's fault reset; answers the faults that were latched),
``{"op": "sdo_read", "position": 3, "index": 9090, "sub_index": 1}``,
``{"op": "sdo_write", ..., "data": "1e000000"}``; answers carry ``"ok": true`` or ``"error"``.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import stat
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Required, TypedDict, cast

from humanoid_prime.drivers.ethercat.sdo_client import SdoClient
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode

if TYPE_CHECKING:
    from humanoid_prime.runtime.switching import SwitchAnswer

SOCKET_ENV = "PRIME_CONTROL_SOCKET"
MAX_SOCKET_PATH_BYTES = 107  # sun_path holds 108 bytes on Linux, the last a NUL
MAX_WAIT_S = 60.0  # the longest a mode request waits for its outcome
MAX_REQUEST_BYTES = 65536  # the largest request is an SDO write of a few bytes
SwitchMode = Callable[[Mode, float], "SwitchAnswer"]  # (mode, seconds to wait for its outcome) -> the outcome
Reply = dict[str, object]  # a JSON object: "ok", then "error" or what the request asked for


class Request(TypedDict, total=False):
    """A request as a client sends it (one JSON object per line); the server converts and checks each field."""

    op: Required[str]  # ping, mode, state, reset, limp, sdo_read or sdo_write
    mode: str
    wait: float  # mode: seconds to wait for the outcome
    position: int  # limp, sdo_*: ring position
    limp: bool
    index: int
    sub_index: int
    data: str  # sdo_write: the bytes in hex


def default_socket_path() -> Path:
    """``$PRIME_CONTROL_SOCKET``, else a per-user path (fixed before any re-exec into a user namespace, where
    the uid reads 0)."""
    if os.environ.get(SOCKET_ENV):
        return Path(os.environ[SOCKET_ENV])
    base = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
    return Path(base) / f"prime-{os.getuid()}" / "control.sock"


class ControlServer:
    """Serves mode requests (handed to ``switch_mode``) and, if given an ``sdo`` client, SDO requests.

    A run claims its socket first, before it touches a bus (a second instance stops there), and attaches
    what it serves once it is up; until then, and after ``detach``, requests are answered "not ready".
    """

    def __init__(self, switch_mode: SwitchMode | None = None, path: str | Path | None = None, *,
                 sdo: SdoClient | None = None, joint_limp: Callable[[int, bool], str] | None = None,
                 on_close: Callable[[], None] | None = None,
                 reset: Callable[[], list[str]] | None = None,
                 state: Callable[[], dict[str, object]] | None = None) -> None:
        self.path = Path(path) if path is not None else default_socket_path()
        self.ready = False
        self.switch_mode: SwitchMode | None = None
        self.reset: Callable[[], list[str]] | None = None
        self.sdo: SdoClient | None = None
        self.joint_limp: Callable[[int, bool], str] | None = None
        self.on_close: Callable[[], None] | None = None  # runs once no request can arrive any more
        self.state: Callable[[], dict[str, object]] | None = None  # the run's latest joints, mode and flags
        if any(h is not None for h in (switch_mode, sdo, joint_limp, on_close, reset, state)):
            self.attach(switch_mode=switch_mode, sdo=sdo, joint_limp=joint_limp, on_close=on_close, reset=reset,
                        state=state)
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def start(self) -> ControlServer:
        check_socket_path(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        if self.path.exists():
            if _answers(self.path):
                raise PrimeError(f"another prime instance already listens on {self.path}")
            self.path.unlink()  # a socket left by a run that is gone (check_socket_path: nothing else)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.bind(str(self.path))
        sock.listen(8)
        sock.settimeout(0.2)
        self._sock = sock
        self._thread = threading.Thread(target=self._serve, name="control-socket", daemon=True)
        self._thread.start()
        return self

    def attach(self, *, switch_mode: SwitchMode | None = None, sdo: SdoClient | None = None,
               joint_limp: Callable[[int, bool], str] | None = None,
               on_close: Callable[[], None] | None = None, reset: Callable[[], list[str]] | None = None,
               state: Callable[[], dict[str, object]] | None = None) -> None:
        """Start answering with these handlers (the run is up)."""
        self.switch_mode, self.sdo, self.joint_limp, self.on_close = switch_mode, sdo, joint_limp, on_close
        self.reset = reset
        self.state = state
        self.ready = True

    def detach(self) -> None:
        """Stop answering for the run (it is tearing down) and run its ``on_close`` once."""
        self.ready = False
        self.switch_mode = self.sdo = self.joint_limp = self.reset = self.state = None
        if self.on_close is not None:
            on_close, self.on_close = self.on_close, None
            on_close()

    def _serve(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            threading.Thread(target=self._handle, args=(conn,), daemon=True).start()

    def _handle(self, conn: socket.socket) -> None:
        with conn:
            conn.settimeout(10.0)
            try:
                reply = self._answer(_parse_request(_recv_line(conn, MAX_REQUEST_BYTES)))
            except (ValueError, KeyError, TypeError) as exc:
                reply = {"ok": False, "error": f"bad request: {exc}"}
            except OSError:
                return
            with contextlib.suppress(OSError):
                conn.sendall(json.dumps(reply).encode() + b"\n")

    def _answer(self, request: Request) -> Reply:
        op = request["op"]
        try:
            if op == "ping":
                return {"ok": True, "ready": self.ready}
            if not self.ready:
                return {"ok": False, "error": "this prime instance is starting up or shutting down; try again"}
            if op == "mode":
                switch = self.switch_mode
                if switch is None:
                    return {"ok": False, "error": "this prime instance runs no mode controllers"}
                wait = float(request.get("wait", 0.0))
                if not 0.0 <= wait <= MAX_WAIT_S:
                    raise ValueError(f"wait must be 0..{MAX_WAIT_S:g} s, got {wait:g}")
                return {"ok": True, **switch(Mode.parse(str(request["mode"])), wait)}
            if op == "state":
                if self.state is None:
                    return {"ok": False, "error": "this prime instance publishes no state"}
                return {"ok": True, **self.state()}
            if op == "reset":
                if self.reset is None:
                    return {"ok": False, "error": "this prime instance drives no hardware that latches faults"}
                return {"ok": True, "faults": self.reset()}
            if op == "limp":
                if self.joint_limp is None:
                    return {"ok": False, "error": "prime limp needs a running `prime calibrate` (or a single-bus "
                                                  "`prime bringup`), where no mode controller commands the eRob"}
                joint = self.joint_limp(int(request["position"]), bool(request["limp"]))
                return {"ok": True, "joint": joint}
            if op in ("sdo_read", "sdo_write"):
                if self.sdo is None:
                    return {"ok": False, "error": "this prime instance has no EtherCAT master"}
                position, index, sub = int(request["position"]), int(request["index"]), int(request["sub_index"])
                if op == "sdo_read":
                    return {"ok": True, "data": self.sdo.sdo_read(position, index, sub).hex()}
                self.sdo.sdo_write(position, index, sub, bytes.fromhex(request["data"]))
                return {"ok": True}
        except (PrimeError, ValueError) as exc:
            return {"ok": False, "error": str(exc)}
        except KeyError as exc:
            return {"ok": False, "error": f"bad request: {op!r} needs the field {exc}"}
        except Exception as exc:  # an answer, never a dead handler: the client gets one line
            return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        return {"ok": False, "error": f"unknown op {op!r}"}

    def close(self) -> None:
        self._stop.set()
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        self.detach()

    def __enter__(self) -> ControlServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def check_socket_path(path: Path) -> None:
    """A control socket path is a free path or a socket (a stale one is replaced): anything else there is somebody's
    file and is never removed; and it must fit a UNIX socket address."""
    if len(os.fsencode(path)) > MAX_SOCKET_PATH_BYTES:
        raise PrimeError(f"control socket path {path} is too long for a UNIX socket ({len(os.fsencode(path))} bytes, "
                         f"at most {MAX_SOCKET_PATH_BYTES}); give a shorter --socket")
    if path.is_dir():
        raise PrimeError(f"control socket path {path} is a folder; give a file path for the socket (--socket)")
    if path.exists() and not stat.S_ISSOCK(path.stat().st_mode):
        raise PrimeError(f"control socket path {path} exists and is not a socket; refusing to replace it "
                         "(give another --socket)")


def _parse_request(line: str) -> Request:
    """A request's JSON; ValueError for one that is not a JSON object, or nests deeper than Python's parser
    recurses (a line of 60,000 brackets fits the size limit)."""
    try:
        request = json.loads(line)
    except RecursionError:
        raise ValueError("nested too deep; a request is one flat JSON object") from None
    if not isinstance(request, dict):
        raise ValueError(f"a request is a JSON object, got {type(request).__name__}")
    return cast(Request, request)


def _recv_line(conn: socket.socket, limit: int | None = None) -> str:
    """One line from ``conn``; beyond ``limit`` bytes a ValueError (a peer cannot grow the server without end)."""
    chunks = []
    size = 0
    while True:
        chunk = conn.recv(4096)
        if not chunk:
            break
        chunks.append(chunk)
        size += len(chunk)
        if limit is not None and size > limit:
            raise ValueError(f"a request is one line of at most {limit} bytes")
        if chunk.endswith(b"\n"):
            break
    return b"".join(chunks).decode("utf-8", "replace")


def request(path: str | Path | None, payload: Request, timeout: float = 5.0) -> Reply:
    """Send one request to the running instance; a missing instance or an error answer raises PrimeError."""
    path = Path(path) if path is not None else default_socket_path()
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(timeout)
            sock.connect(str(path))
            sock.sendall(json.dumps(payload).encode() + b"\n")
            text = _recv_line(sock)
    except (FileNotFoundError, ConnectionRefusedError):
        raise PrimeError(f"no running prime instance listens on {path} (start prime sim or prime bringup, or give "
                         "the --socket it answers on)") from None
    except OSError as exc:
        raise PrimeError(f"could not reach {path}: {exc.strerror or exc}") from None
    try:
        reply: Reply = json.loads(text)
    except ValueError:
        raise PrimeError(f"garbled answer from {path}") from None
    if not reply.get("ok"):
        raise PrimeError(str(reply.get("error") or f"no answer from {path}"))
    return reply


def _answers(path: Path) -> bool:
    try:
        request(path, {"op": "ping"}, timeout=0.5)
        return True
    except PrimeError:
        return False


def send_mode_request(mode: Mode, path: str | Path | None = None, wait: float = 0.0) -> SwitchAnswer:
    """Ask the running instance to switch to ``mode`` and, with ``wait`` seconds, for what became of it
    (``runtime.switching``); a refused mode raises PrimeError."""
    reply = request(path, {"op": "mode", "mode": mode.value, "wait": wait}, timeout=wait + 5.0)
    return cast("SwitchAnswer", reply)  # the server's ``switch_mode`` answer, with "ok"


def request_state(path: str | Path | None = None, timeout: float = 2.0) -> Reply:
    """The running instance's latest joint positions, mode and safety flags."""
    return request(path, {"op": "state"}, timeout=timeout)


def send_reset_request(path: str | Path | None = None) -> list[str]:
    """The operator's fault reset on the running instance; the faults latched when it was asked."""
    faults = cast(list[object], request(path, {"op": "reset"})["faults"])  # as ``_answer`` sends them
    return [str(fault) for fault in faults]


class SocketSdoClient:
    """SDO through the control socket of the running process that owns the EtherCAT master.

    ``mark_limp`` tells that process a joint is going limp (its CSP target then follows the actual
    position, so sweeping it builds no following error) or holds again."""

    def __init__(self, path: str | Path | None = None, timeout: float = 5.0) -> None:
        self.path = Path(path) if path is not None else default_socket_path()
        self.timeout = timeout

    def sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        reply = request(self.path, {"op": "sdo_read", "position": position, "index": index,
                                    "sub_index": sub_index}, self.timeout)
        return bytes.fromhex(cast(str, reply["data"]))  # as ``_answer`` sends it

    def sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        request(self.path, {"op": "sdo_write", "position": position, "index": index, "sub_index": sub_index,
                            "data": data.hex()}, self.timeout)

    def mark_limp(self, position: int, limp: bool) -> None:
        request(self.path, {"op": "limp", "position": position, "limp": limp}, self.timeout)
