"""The lockstep Prime's buses in this process: ``LockstepRing``, an ``EthercatMaster`` whose exchange hands the process
image to the emulated eRob's objects in Prime's PDO layout and their inputs back, and ``LockstepCan``, a python-can
bus on which a frame the host sends reaches the emulated Sito motors as it is sent and their feedback reaches the
host's receive thread before the next tick (``virtual.lockstep``)."""


import threading
from collections import deque
from collections.abc import Callable, Sequence

import can
import numpy as np

from humanoid_prime.drivers.erob import objects as obj
from humanoid_prime.drivers.ethercat.errors import SdoError
from humanoid_prime.drivers.ethercat.master import EthercatMaster
from humanoid_prime.drivers.ethercat.ring import SlaveInfo
from humanoid_prime.drivers.ethercat.wire import AlState
from humanoid_prime.errors import PrimeError
from humanoid_prime.virtual.ring.drive import ErobDrive
from humanoid_prime.virtual.ring.od import SdoAbort
from humanoid_prime.virtual.ring.pdo import PdoCodec

# How long the host's receive thread may take to collect one tick's feedback before the rig gives up: a guard
# against a dead thread, never a pace (a loaded machine takes milliseconds).
DRAIN_TIMEOUT_S = 60.0


class _Instant:
    """The ring's bring-up clock: a wait passes at once, as the drives answer within each exchange."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


class LockstepRing(EthercatMaster):
    """The eRob drives (``drives``, ring order) as a master sees them, without a wire: ``send`` hands each drive
    its outputs (Prime's RxPDO, decoded into the drive's objects) once its slave is in OP, ``receive`` fills the
    inputs from the drives' objects after they have measured ``q``/``qd`` (raw rad, rad/s, one per drive, set by
    the world). ``lock`` is held while a drive changes, by the exchange and by the world alike: the master's keeper
    thread may exchange while the world steps."""

    def __init__(self, drives: Sequence[ErobDrive], *, update_rate: float) -> None:
        clock = _Instant()
        super().__init__("lockstep", update_rate=update_rate, clock=clock, sleep=clock.sleep)
        self.drives = tuple(drives)
        n = len(self.drives)
        self.q, self.qd = np.zeros(n), np.zeros(n)
        self.lock = threading.Lock()
        self._states = [AlState.PRE_OP] * n
        self._rx = [_codec(drive, obj.RXPDO) for drive in self.drives]
        self._tx = [_codec(drive, obj.TXPDO) for drive in self.drives]

    def _discover(self) -> Sequence[SlaveInfo]:
        return [SlaveInfo(k, "eRob (lockstep)", int(drive.od.value(obj.IDENTITY, 1)),
                          int(drive.od.value(obj.IDENTITY, 2)), int(drive.od.value(obj.IDENTITY, 3)), AlState.PRE_OP)
                for k, drive in enumerate(self.drives)]

    def _configure(self) -> None:
        n = len(self.drives)
        self.outputs = np.zeros(n, self.outputs.dtype)
        self.inputs = np.zeros(n, self.inputs.dtype)
        self.expected_wkc = 3 * n
        for k, drive in enumerate(self.drives):  # read in PRE-OP, as SoemMaster does
            self.store_rated_torque(k, drive.od.upload(obj.RATED_TORQUE, 0))
        self._states = [AlState.SAFE_OP] * n

    def _request_op(self) -> None:
        self._states = [AlState.OP] * len(self.drives)

    def _read_states(self) -> list[tuple[int, int]]:
        return [(state, 0) for state in self._states]

    def _advance(self, slaves: Sequence[tuple[int, int]]) -> None:
        pass  # every slave reaches OP when asked

    def _send(self) -> None:
        image = bytearray(self.outputs.tobytes())
        with self.lock:
            for k, (drive, codec, state) in enumerate(zip(self.drives, self._rx, self._states, strict=True)):
                if state == AlState.OP:
                    codec.unpack(image, k * codec.size)
                    drive.process_outputs()

    def _receive(self) -> int:
        image = bytearray(self.inputs.nbytes)
        with self.lock:
            for k, (drive, codec) in enumerate(zip(self.drives, self._tx, strict=True)):
                drive.update_feedback(float(self.q[k]), float(self.qd[k]))
                codec.pack(image, k * codec.size)
        self.inputs[:] = np.frombuffer(image, self.inputs.dtype)
        return self.expected_wkc

    def _sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        with self.lock:
            try:
                return self.drives[position].od.upload(index, sub_index)
            except SdoAbort as exc:
                raise SdoError(position, index, sub_index, f"aborted with 0x{exc.code:08X} ({exc})", exc.code) \
                    from None

    def _sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        with self.lock:
            try:
                self.drives[position].od.download(index, sub_index, data)
            except SdoAbort as exc:
                raise SdoError(position, index, sub_index, f"aborted with 0x{exc.code:08X} ({exc})", exc.code) \
                    from None

    def _close(self) -> None:
        self._states = [AlState.PRE_OP] * len(self.drives)


def _codec(drive: ErobDrive, layout: Sequence[obj.PdoEntry]) -> PdoCodec:
    """The drive's side of Prime's PDO ``layout``: its objects, and the pad bytes it ignores."""
    return PdoCodec([None if e.index == 0 else drive.od.entry(e.index, e.sub_index) for e in layout],
                    [len(e.fmt) if e.index == 0 else 0 for e in layout])


class LockstepCan:
    """One CAN bus in this process between the host (``host``, a python-can bus) and the motors' side
    (``motors``): a frame the host sends is handed to ``on_host_frame`` as it is sent; frames the motors send
    wait for the host's receive thread, and ``drain()`` returns once that thread has handled every one."""

    def __init__(self, on_host_frame: Callable[[], None]) -> None:
        self.on_host_frame = on_host_frame
        self.to_motors: deque[can.Message] = deque()
        self.to_host: deque[can.Message] = deque()
        self.changed = threading.Condition()
        self.delivered = 0  # frames the motors sent
        self.handled = 0  # frames the host's reader took and came back from
        self.holding = False  # the reader took a frame and has not come back for the next
        self.closed = False
        self.host = _HostEnd(self)
        self.motors = _MotorEnd(self)

    def drain(self) -> None:
        with self.changed:
            if not self.changed.wait_for(lambda: self.handled == self.delivered or self.closed, DRAIN_TIMEOUT_S):
                raise PrimeError(f"the host's CAN receive thread took {self.handled} of {self.delivered} frames "
                                 f"within {DRAIN_TIMEOUT_S:g} s; it has stopped")

    def close(self) -> None:
        with self.changed:
            self.closed = True
            self.changed.notify_all()
        self.host.shutdown()
        self.motors.shutdown()


class _HostEnd(can.BusABC):
    def __init__(self, line: LockstepCan) -> None:
        self.line = line
        self.channel_info = "lockstep"
        super().__init__(channel="lockstep")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.line.to_motors.append(msg)
        self.line.on_host_frame()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        line = self.line
        with line.changed:
            if line.holding:  # back from handling the frame it took: that one is done
                line.holding = False
                line.handled += 1
                line.changed.notify_all()
            if not line.to_host:
                line.changed.wait(timeout)
            if not line.to_host:
                return None, False
            line.holding = True
            return line.to_host.popleft(), False


class _MotorEnd(can.BusABC):
    def __init__(self, line: LockstepCan) -> None:
        self.line = line
        self.channel_info = "lockstep"
        super().__init__(channel="lockstep")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        line = self.line
        with line.changed:
            line.to_host.append(msg)
            line.delivered += 1
            line.changed.notify_all()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.line.to_motors.popleft() if self.line.to_motors else None), False
