"""The CAN transport under the Sito wrists: opening a python-can bus from the hardware file, telling a
dead interface from a full transmit queue, the exact on-wire length of a frame (for bus load), and the
fastest cycle the wrists' traffic fits on the bus (``bus_cycle``)."""

from __future__ import annotations

import contextlib
import errno
import math

import can

from humanoid_prime.config.hardware import HardwareConfig
from humanoid_prime.drivers.sito.protocol import FEEDBACK_INTERVAL_MS, ID_PREFIX, ID_PREFIX_MASK
from humanoid_prime.errors import PrimeError

SITO_FILTERS = [{"can_id": ID_PREFIX, "can_mask": ID_PREFIX_MASK, "extended": True}]

# SocketCAN error-frame classes (linux/can/error.h), found in the arbitration id of an error frame.
CAN_ERR_CRTL = 0x004
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_RESTARTED = 0x100

CAN_EXTENDED_FRAME_BITS = 67  # SOF, 29-bit id, SRR, IDE, RTR, r1, r0, DLC, CRC 15 + delimiter, ACK 2, EOF 7, IFS 3
CAN_STUFFED_BITS = 54  # the bits stuffing applies to (SOF through CRC), besides the data
FRAMES_PER_WRIST = 3  # per bus cycle: the host's command, and the wrist's 0xB1 and 0xB2 feedback
BUS_BUDGET = 0.6  # of the bit rate the cyclic frames may take, at worst-case stuffing: the rest is room for
# gain frames, arbitration and error frames, so that a frame never waits a whole cycle for the bus

# errno values that mean the interface itself is gone or down, as opposed to a full queue.
_INTERFACE_DOWN_ERRNOS = frozenset({errno.ENETDOWN, errno.ENODEV, errno.ENXIO, errno.EBADF, errno.ENETUNREACH})


def can_frame_bits(data_bytes: int = 8, *, worst_stuffing: bool = False) -> int:
    """Bit times of one extended CAN data frame; with ``worst_stuffing`` one stuff bit per four stuffable bits."""
    bits = CAN_EXTENDED_FRAME_BITS + 8 * data_bytes
    if worst_stuffing:
        bits += (CAN_STUFFED_BITS + 8 * data_bytes - 1) // 4
    return bits


def bus_cycle(update_rate: float, wrists: int, bitrate: float, budget: float = BUS_BUDGET) -> tuple[int, int]:
    """(ticks per bus cycle, feedback interval in ms) for ``wrists`` motors at control rate ``update_rate``.

    Each bus cycle carries a command to every wrist and its 0xB1 and 0xB2 feedback. Up to about 300 Hz with
    four wrists at 1 Mbit/s that is every tick, with feedback at the control period. Above, the frames would
    not fit the period (at 1 kHz, 12 frames take 1.6 to 1.9 ms of a 1 ms tick), so the commands go out every
    n-th tick, the fewest ticks whose time holds the cycle within ``budget`` of the bus, and the wrists stream
    feedback at that cycle (whole milliseconds, rounded up)."""
    if not math.isfinite(update_rate) or update_rate <= 0:
        raise ValueError(f"control rate must be a positive number of Hz, got {update_rate!r}")
    cycle_s = wrists * FRAMES_PER_WRIST * can_frame_bits(worst_stuffing=True) / (budget * bitrate)
    every = max(1, math.ceil(cycle_s * update_rate - 1e-9))
    feedback_ms = math.ceil(1000.0 * every / update_rate - 1e-9)
    return every, min(max(feedback_ms, 1), max(FEEDBACK_INTERVAL_MS))


def open_bus(hardware: HardwareConfig, *, interface: str | None = None, channel: str | None = None) -> can.BusABC:
    """Open the Sito bus: interface and channel from ``buses.can`` unless overridden.

    On SocketCAN the Sito id filter runs in the kernel; error frames still arrive (separate filter).
    """
    interface = interface or hardware.can.interface
    channel = channel or hardware.can.channel
    can_filters = SITO_FILTERS if interface == "socketcan" else None
    try:
        return can.Bus(interface=interface, channel=channel, bitrate=hardware.can.bitrate, can_filters=can_filters)
    except (OSError, can.CanError, ImportError, ValueError) as exc:
        _shut_down_unfinished(exc)
        if interface == "socketcan":
            fix = f"bring it up with: sudo ip link set {channel} up type can bitrate {hardware.can.bitrate}"
        else:
            fix = f"check buses.can in {hardware.path.name} or the --interface/--channel options"
        raise PrimeError(f"cannot open CAN channel {channel!r} ({interface}): {exc}; {fix}") from None


def _shut_down_unfinished(exc: BaseException) -> None:
    """Shut down the bus whose constructor raised ``exc`` after python-can's base had counted it open
    (udp_multicast opens its socket after ``BusABC.__init__``): otherwise its finaliser logs "... was not properly
    shut down" after our one line. python-can gives no handle on it but the constructor's frame (its maintainers'
    answer was that a shutdown must cope with a half-built bus: hardbyte/python-can#1519)."""
    tb = exc.__traceback__
    while tb is not None:
        bus = tb.tb_frame.f_locals.get("self")
        if isinstance(bus, can.BusABC):
            with contextlib.suppress(Exception):
                bus.shutdown()  # what the interface did open (a socket), if its shutdown copes
            can.BusABC.shutdown(bus)  # and the base's own: the bus counts as shut down
            return
        tb = tb.tb_next


def is_interface_down(exc: BaseException) -> bool:
    """True when a send/receive failure means the interface is down or gone (not merely a full queue)."""
    code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
    if code in _INTERFACE_DOWN_ERRNOS:
        return True
    return "closed bus" in str(exc)


def is_queue_full(exc: BaseException) -> bool:
    """True when a send failed because the transmit queue is full (ENOBUFS on SocketCAN)."""
    code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
    return code == errno.ENOBUFS or (code is None and not is_interface_down(exc))


def crc15(bits: list[int]) -> int:
    crc = 0
    for bit in bits:
        feedback = bit ^ (crc >> 14)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= 0x4599
    return crc


def to_bits(value: int, width: int) -> list[int]:
    return [(value >> i) & 1 for i in range(width - 1, -1, -1)]


def stuff_bit_count(bits: list[int]) -> int:
    """Stuff bits a transmitter inserts: one after every five equal bits (stuff bits count in the next run)."""
    count = 0
    run_bit, run = -1, 0
    for bit in bits:
        if bit == run_bit:
            run += 1
        else:
            run_bit, run = bit, 1
        if run == 5:
            count += 1
            run_bit, run = 1 - bit, 1
    return count


def frame_bits(message: can.Message) -> int:
    """Exact bit times of a classic CAN data or remote frame on the wire, including stuff bits,
    CRC, delimiters, ACK, end of frame and the 3-bit intermission."""
    dlc = min(message.dlc, 8)
    data = bytes(message.data[:dlc]) if not message.is_remote_frame else b""
    rtr = 1 if message.is_remote_frame else 0
    if message.is_extended_id:
        ident = message.arbitration_id & 0x1FFFFFFF
        head = [0] + to_bits(ident >> 18, 11) + [1, 1] + to_bits(ident & 0x3FFFF, 18) + [rtr, 0, 0]
    else:
        head = [0] + to_bits(message.arbitration_id & 0x7FF, 11) + [rtr, 0, 0]
    bits = head + to_bits(dlc, 4)
    for byte in data:
        bits += to_bits(byte, 8)
    bits += to_bits(crc15(bits), 15)
    # CRC delimiter, ACK slot, ACK delimiter, 7 EOF bits, 3 intermission bits: never stuffed.
    return len(bits) + stuff_bit_count(bits) + 13
