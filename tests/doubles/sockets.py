"""A packet socket being opened while another NIC sends: the frame goes out of ``lo`` just before each packet socket
is bound (the moment a socket opened for a protocol would take every NIC's frames)."""

from __future__ import annotations

import contextlib
import socket
from collections.abc import Iterator

import pytest


@contextlib.contextmanager
def frame_elsewhere_at_each_bind(frame: bytes) -> Iterator[None]:
    """Within the block, every packet socket's ``bind`` first sends ``frame`` out of another NIC (``lo``)."""
    other = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0)
    other.bind(("lo", 0))
    bind = socket.socket.bind

    def bind_after_a_frame_elsewhere(sock: socket.socket, address: object) -> None:
        if sock.family == socket.AF_PACKET:
            other.send(frame)
        bind(sock, address)

    try:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(socket.socket, "bind", bind_after_a_frame_elsewhere)
            yield
    finally:
        other.close()
