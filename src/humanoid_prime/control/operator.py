"""Mode requests from a second terminal: a small UNIX-socket server inside a running ``prime sim`` or
``prime bringup``, and the client behind ``prime switch MODE``.

One request per connection, one line each way: the client sends a mode name, the server answers
``ok MODE`` once the request is queued (it lands between two ticks) or ``error ...``.
"""

from __future__ import annotations

import contextlib
import os
import socket
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode


def default_socket_path() -> Path:
    base = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
    return Path(base) / f"prime-{os.getuid()}" / "mode.sock"


class ModeRequestServer:
    """Accepts mode names on a UNIX socket and hands them to ``request`` (e.g. manager.request_mode)."""

    def __init__(self, request: Callable[[Mode], None], path: str | Path | None = None) -> None:
        self.request = request
        self.path = Path(path) if path is not None else default_socket_path()
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def start(self) -> ModeRequestServer:
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        if self.path.exists():
            if _answers(self.path):
                raise PrimeError(f"another prime instance already listens on {self.path}")
            self.path.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.bind(str(self.path))
        sock.listen(4)
        sock.settimeout(0.2)
        self._sock = sock
        self._thread = threading.Thread(target=self._serve, name="mode-requests", daemon=True)
        self._thread.start()
        return self

    def _serve(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                conn.settimeout(1.0)
                try:
                    text = conn.recv(256).decode("utf-8", "replace").strip()
                    if text == "ping":
                        reply = "ok ping"
                    else:
                        mode = Mode.parse(text)
                        self.request(mode)
                        reply = f"ok {mode.value}"
                except (ValueError, PrimeError) as exc:
                    reply = f"error {exc}"
                except OSError:
                    continue
                with contextlib.suppress(OSError):
                    conn.sendall(reply.encode() + b"\n")

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

    def __enter__(self) -> ModeRequestServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def _exchange(path: Path, text: str, timeout: float) -> str:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout)
        sock.connect(str(path))
        sock.sendall(text.encode() + b"\n")
        return sock.recv(512).decode("utf-8", "replace").strip()


def _answers(path: Path) -> bool:
    try:
        return _exchange(path, "ping", 0.5) == "ok ping"
    except OSError:
        return False


def send_mode_request(mode: Mode, path: str | Path | None = None, timeout: float = 2.0) -> str:
    """Ask the running instance at ``path`` to switch to ``mode``; returns the server's answer."""
    path = Path(path) if path is not None else default_socket_path()
    try:
        reply = _exchange(path, mode.value, timeout)
    except (FileNotFoundError, ConnectionRefusedError):
        raise PrimeError(f"no running prime sim or bringup listens on {path}") from None
    except OSError as exc:
        raise PrimeError(f"could not reach {path}: {exc.strerror or exc}") from None
    if not reply.startswith("ok "):
        raise PrimeError(reply.removeprefix("error ").strip() or f"no answer from {path}")
    return reply
