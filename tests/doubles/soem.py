"""A test double of pysoem's ``Master``: SOEM's work done in Python over the emulated ring in-process
(``doubles.link.RingHub``), on emulated time, with SOEM's own ways, weaknesses included:

- its frame layer (nicdrv.c): 16 frame buffers used in turn, a frame resent under the same index until its
  timeout, and a reply filed by its frame's index alone, into whichever datagram holds that index (a late reply
  too, once its index is in use again);
- its mailbox (ethercatmain.c ``ecx_mbxsend``/``ecx_mbxreceive``, ethercatcoe.c ``ecx_SDOread``/``ecx_SDOwrite``):
  the first message in the read mailbox taken for the answer, checked by object index only on upload; a mailbox
  read whose frame did not come back repeated with a "repeat request" that writes SM1's status word back from the
  copy read last;
- its ring scan, PDO layout (``ecx_readPDOmap``, whose read-back sizes the process image), DC set-up, the cycle
  (LRW + FRMW of the reference clock's time), recovery and register access (``_fprd``/``_fpwr``).

``FakeSoemMaster.ring`` says, per interface name, which hub and clock the next master uses. While a master has a
process image, emulated time that passes with no frame of the cycle (a test waiting out a timeout) carries the
cycle on at its period, as the master's keeper thread would.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Callable, Sequence

import pysoem

from doubles.link import EmulatedClock, RingHub
from humanoid_prime.drivers.ethercat.link import Request, build_frame, frame_index
from humanoid_prime.drivers.ethercat.wire import SII_WORD_VENDOR, Command
from humanoid_prime.virtual.ring.firmware import sii_content

EC_MAXBUF = 16
EC_TIMEOUTRET = 0.002  # a frame's own timeout
EC_TIMEOUTRET3 = 0.006
EC_TIMEOUTSAFE = 0.020
EC_TIMEOUTTXM = 0.020
EC_TIMEOUTRXM = 0.700
EC_TIMEOUTSTATE = 2.0
EC_LOCALDELAY = 0.0002
STATION_BASE = 0x1001
_HEADER = struct.Struct("<BBHHHH")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


class _Reply:
    def __init__(self, data: bytes, wkc: int, command: int) -> None:
        self.data, self.wkc, self.command = data, wkc, command


def _datagrams(frame: bytes) -> list[tuple[int, bytes, int]]:
    """(command, data, wkc) of each datagram of a reply frame, as far as it parses."""
    out, offset = [], 16
    while offset + 12 <= len(frame):
        command, _index, _adp, _ado, length_field, _irq = _HEADER.unpack_from(frame, offset)
        length = length_field & 0x07FF
        if offset + 12 + length > len(frame):
            break
        data = frame[offset + 10:offset + 10 + length]
        out.append((command, bytes(data), _U16.unpack_from(frame, offset + 10 + length)[0]))
        offset += 12 + length
        if not length_field & 0x8000:
            break
    return out


class SoemFrames:
    """SOEM's frame layer over ``hub``: buffers 0..15, each reply filed by its index alone."""

    EMPTY, TX, RCVD = 0, 2, 3

    def __init__(self, hub: RingHub, clock: EmulatedClock, base: int = 0) -> None:
        self.hub = hub
        self.clock = clock
        self.base = base  # the index its frames carry for buffer 0 (SOEM's: 0)
        self.port = hub.port(range(base, base + EC_MAXBUF))
        self.state = [self.EMPTY] * EC_MAXBUF
        self.filed: list[bytes | None] = [None] * EC_MAXBUF
        self.last = 0
        self.lock = threading.RLock()

    def index(self) -> int:
        with self.lock:
            for step in range(1, EC_MAXBUF + 1):
                idx = (self.last + step) % EC_MAXBUF
                if self.state[idx] == self.EMPTY:
                    self.last = idx
                    self.state[idx] = self.TX
                    return idx
            raise RuntimeError("no free SOEM frame buffer")

    def send(self, idx: int, requests: Sequence[Request]) -> None:
        self.hub.send(build_frame(self.base + idx, requests))

    def wait(self, idx: int, timeout_s: float) -> bytes | None:
        """ecx_waitinframe: this index's frame, or one filed for it meanwhile; others filed for their waiters."""
        deadline = self.clock() + timeout_s
        while True:
            with self.lock:
                if self.state[idx] == self.RCVD:
                    frame, self.filed[idx] = self.filed[idx], None
                    return frame
            remaining = deadline - self.clock()
            if remaining <= 0:
                return None
            frame = self.port.receive(remaining)
            if frame is None:
                continue
            got = frame_index(frame)
            got = None if got is None else got - self.base
            with self.lock:
                if got == idx:
                    return frame
                if got is not None and got < EC_MAXBUF and self.state[got] == self.TX:
                    self.filed[got] = frame  # a late frame lands in whichever datagram holds its index now
                    self.state[got] = self.RCVD

    def release(self, idx: int) -> None:
        with self.lock:
            self.state[idx] = self.EMPTY
            self.filed[idx] = None

    def srconfirm(self, requests: Sequence[Request], timeout_s: float) -> list[_Reply] | None:
        """Send and wait, resending under the same index every EC_TIMEOUTRET while no frame came back, until
        ``timeout_s``; the replies, copied from whatever frame came back with that index (None: none did)."""
        idx = self.index()
        deadline = self.clock() + timeout_s
        try:
            while True:
                self.send(idx, requests)
                frame = self.wait(idx, min(EC_TIMEOUTRET, max(deadline - self.clock(), 0.0)))
                if frame is not None:
                    got = _datagrams(frame)
                    replies = []
                    for k, request in enumerate(requests):
                        command, data, wkc = got[k] if k < len(got) else (request.command, b"", 0)
                        replies.append(_Reply(data[:request.length].ljust(request.length, b"\0"), wkc, command))
                    return replies  # a frame came back: answered or not, it is the reply (only a lost one is resent)
                if self.clock() >= deadline:
                    return None
        finally:
            self.release(idx)


class FakeSoemSlave:
    """One ``CdefSlave``: identity from the SII, SOEM's mailbox and register access, ``config_func``."""

    def __init__(self, master: FakeSoemMaster, position: int) -> None:
        self._master = master
        self.position = position
        self.station = STATION_BASE + position
        content = sii_content(master.hub.ring.options, 0)
        image = master.hub.ring.slaves[position].esc.eeprom.image  # the identity as this slave's SII holds it
        self.name = "eRob"
        self.man, self.id, self.rev = struct.unpack_from("<III", image, 2 * SII_WORD_VENDOR)
        if FakeSoemMaster.misread.get(position, 0) > 0:  # an EEPROM read that failed in this scan
            FakeSoemMaster.misread[position] -= 1
            self.man = self.id = 0
        self.mailbox = (content.sync_managers[0].start, content.sync_managers[0].length,
                        content.sync_managers[1].start, content.sync_managers[1].length)
        self.state, self.al_status = pysoem.NONE_STATE, 0
        self.config_func: Callable[[int], None] | None = None
        self.output, self.input = b"", b""
        self.obits = self.ibits = 0
        self.mbx_cnt = 0
        self._callbacks: list[Callable] = []

    def add_emergency_callback(self, callback: Callable) -> None:
        self._callbacks.append(callback)

    # ---- registers ------------------------------------------------------------------------------------------
    def _fprd(self, address: int, size: int, timeout_us: int = 2000) -> bytes:
        request = Request(Command.FPRD, self.station, address, size=size)
        replies = self._master.frames.srconfirm([request], timeout_us / 1e6)
        if replies is None or replies[0].wkc != 1:
            raise pysoem.WkcError()
        return replies[0].data

    def _fpwr(self, address: int, data: bytes, timeout_us: int = 2000) -> None:
        replies = self._master.frames.srconfirm([Request(Command.FPWR, self.station, address, data=bytes(data))],
                                                timeout_us / 1e6)
        if replies is None or replies[0].wkc != 1:
            raise pysoem.WkcError()

    def _rd(self, address: int, size: int, timeout_s: float = EC_TIMEOUTRET) -> tuple[int, bytes]:
        replies = self._master.frames.srconfirm([Request(Command.FPRD, self.station, address, size=size)], timeout_s)
        return (0, bytes(size)) if replies is None else (replies[0].wkc, replies[0].data)

    def _wr(self, address: int, data: bytes, timeout_s: float = EC_TIMEOUTRET) -> int:
        request = Request(Command.FPWR, self.station, address, data=bytes(data))
        replies = self._master.frames.srconfirm([request], timeout_s)
        return 0 if replies is None else replies[0].wkc

    def write_state(self) -> int:
        return self._wr(0x0120, _U16.pack(self.state))

    def state_check(self, expected_state: int, timeout: int = 2000) -> int:
        clock, deadline = self._master.clock, self._master.clock() + timeout / 1e6
        while True:
            wkc, data = self._rd(0x0130, 2)
            state = _U16.unpack(data)[0] if wkc else 0
            self.state = state
            if state == expected_state or clock() >= deadline:
                return state
            clock.sleep(0.001)

    def dc_sync(self, act: bool, sync0_cycle_time: int, sync0_shift_time: int = 0, sync1_cycle_time=None) -> None:
        """ecx_dcsync0."""
        self._wr(0x0981, b"\x00")
        self._wr(0x0980, b"\x00")
        _wkc, data = self._rd(0x0910, 8)
        now = _U64.unpack(data)[0]
        start = ((now + 100_000_000) // sync0_cycle_time) * sync0_cycle_time + sync0_cycle_time
        self._wr(0x0990, _U64.pack(start))
        self._wr(0x09A0, _U32.pack(sync0_cycle_time))
        self._wr(0x0981, b"\x03" if act else b"\x00")

    def recover(self, timeout: int = 500) -> int:
        """ecx_recover_slave: its station address read by position; a slave found without one gets it back."""
        frames = self._master.frames
        replies = frames.srconfirm([Request(Command.APRD, (-self.position) & 0xFFFF, 0x0010, size=2)], timeout / 1e6)
        if replies is None or replies[0].wkc <= 0:
            return 0
        address = _U16.unpack(replies[0].data)[0]
        if address == self.station:
            return 1
        if address == 0:
            frames.srconfirm([Request(Command.APWR, (-self.position) & 0xFFFF, 0x0010, data=_U16.pack(self.station))],
                             timeout / 1e6)
            return 1
        return 0

    # ---- mailbox --------------------------------------------------------------------------------------------
    def _mbxreceive(self, timeout_s: float) -> tuple[int, bytes]:
        """ecx_mbxreceive, with its repeat request."""
        clock = self._master.clock
        _out_start, _out_size, in_start, in_size = self.mailbox
        deadline = clock() + timeout_s
        while True:
            wkc, data = self._rd(0x080D, 2)
            sm_stat = _U16.unpack(data)[0]
            full = wkc > 0 and sm_stat & 0x08
            if not full and timeout_s > EC_LOCALDELAY:
                clock.sleep(EC_LOCALDELAY)
            if full or clock() >= deadline:
                break
        if not full:
            return 0, b""
        while True:
            wkc, message = self._rd(in_start, in_size)
            if wkc > 0 and message[5] & 0x0F == 0x03 and len(message) >= 8 and message[7] >> 4 == 0x01:
                code = _U16.unpack_from(message, 8)[0]
                for callback in self._callbacks:
                    callback(pysoem.Emergency(self.position + 1, code, 0, 0, 0, 0))
                wkc = 0
            elif wkc <= 0:  # read mailbox lost: toggle the repeat request in the status word just read
                sm_stat ^= 0x0200
                self._wr(0x080D, _U16.pack(sm_stat))
                while clock() < deadline:
                    wkc2, control = self._rd(0x080F, 1)
                    if wkc2 > 0 and control[0] & 0x02 == (sm_stat >> 8) & 0x02:
                        break
                while clock() < deadline:
                    wkc2, data = self._rd(0x080D, 2)
                    sm_stat = _U16.unpack(data)[0]
                    if wkc2 > 0 and sm_stat & 0x08:
                        break
                    clock.sleep(EC_LOCALDELAY)
            if wkc > 0 or clock() >= deadline:
                return wkc, message

    def _mbxsend(self, payload: bytes) -> int:
        """ecx_mbxsend: wait for the write mailbox to be empty, then write the message with the next counter."""
        clock = self._master.clock
        out_start, out_size, _in_start, _in_size = self.mailbox
        deadline = clock() + EC_TIMEOUTTXM
        while True:
            wkc, data = self._rd(0x0805, 1)
            if wkc > 0 and not data[0] & 0x08:
                break
            if clock() >= deadline:
                return 0
            clock.sleep(EC_LOCALDELAY)
        self.mbx_cnt = self.mbx_cnt % 7 + 1
        message = struct.pack("<HHBB", len(payload), 0, 0, 0x03 | (self.mbx_cnt << 4)) + payload
        return self._wr(out_start, message.ljust(out_size, b"\0"), EC_TIMEOUTRET3)

    def _sdo(self, payload: bytes, index: int, sub: int, timeout_s: float) -> bytes:
        self._mbxreceive(0.0)  # empty the slave's read mailbox first
        if self._mbxsend(payload) <= 0:
            raise pysoem.WkcError(message="mailbox send", wkc=0)
        wkc, message = self._mbxreceive(timeout_s)
        if wkc <= 0:
            raise pysoem.WkcError(message="no reply", wkc=wkc)
        return message

    def sdo_write(self, index: int, sub: int, data: bytes, ca: bool = False, release_gil: bool = False) -> None:
        """ecx_SDOwrite, expedited: the reply accepted when object and sub-index match."""
        payload = struct.pack("<HBHB", 0x2000, 0x23 | ((4 - len(data)) << 2), index, sub) + bytes(data).ljust(4, b"\0")
        message = self._sdo(payload, index, sub, self._master.sdo_write_timeout / 1e6)
        command, got_index, got_sub = struct.unpack_from("<BHB", message, 8)
        if message[7] >> 4 == 0x03 and (got_index, got_sub) == (index, sub):
            return
        self._raise_unexpected(message, index, sub)

    def sdo_read(self, index: int, sub: int, size: int = 256, release_gil: bool = False) -> bytes:
        """ecx_SDOread: the reply accepted when its object index matches (not its sub-index, nor its kind)."""
        return self._upload(index, sub, self._master.sdo_read_timeout / 1e6)

    def _upload(self, index: int, sub: int, timeout_s: float) -> bytes:
        payload = struct.pack("<HBHBI", 0x2000, 0x40, index, sub, 0)
        message = self._sdo(payload, index, sub, timeout_s)
        command, got_index = message[8], _U16.unpack_from(message, 9)[0]
        if message[5] & 0x0F == 0x03 and message[7] >> 4 == 0x03 and got_index == index:
            if command & 0x02:
                return message[12:12 + 4 - ((command >> 2) & 0x03)]
            length = _U32.unpack_from(message, 12)[0]
            return message[16:16 + length]  # a download's reply reads as 0 bytes here
        self._raise_unexpected(message, index, sub)

    def _raise_unexpected(self, message: bytes, index: int, sub: int) -> None:
        if message[8] == 0x80:
            code = _U32.unpack_from(message, 12)[0]
            raise pysoem.SdoError(self.position + 1, index, sub, code, "SDO abort")
        raise pysoem.PacketError(self.position + 1, 1)

    def read_pdo_map(self) -> tuple[int, int]:
        """ecx_readPDOmap: (output bits, input bits) from 0x1C00 and the assigned PDOs, as SOEM counts them."""
        sizes = {3: 0, 4: 0}
        count = self._try_upload(0x1C00, 0)
        if count is None or count[:1] == b"" or count[0] <= 2:
            return 0, 0
        for sm in range(2, min(count[0], 8)):
            kind = self._try_upload(0x1C00, sm + 1)
            if kind and kind[0] in (3, 4):
                sizes[kind[0]] += self._read_assign(0x1C10 + sm)
        return sizes[3], sizes[4]

    def _read_assign(self, assign: int) -> int:
        bits = 0
        count = self._try_upload(assign, 0)
        for a in range(1, (count[0] if count else 0) + 1):
            raw = self._try_upload(assign, a) or b""
            pdo = _U16.unpack(raw[:2].ljust(2, b"\0"))[0]
            if not pdo:
                continue
            entries = self._try_upload(pdo, 0) or b"\0"
            for e in range(1, entries[0] + 1):
                raw = (self._try_upload(pdo, e) or b"").ljust(4, b"\0")
                bits += raw[0] if raw[0] < 0xFF else 0
        return bits

    def _try_upload(self, index: int, sub: int) -> bytes | None:
        try:
            return self._upload(index, sub, EC_TIMEOUTRXM)
        except (pysoem.WkcError, pysoem.SdoError, pysoem.PacketError) as exc:
            self._master.errors.append(exc)
            return None


class FakeSoemMaster:
    """Stands in for ``pysoem.Master``; ``FakeSoemMaster.ring[interface] = (hub, clock)`` gives its ring."""

    ring: dict[str, tuple[RingHub, EmulatedClock]] = {}
    last: FakeSoemMaster | None = None
    index_base = 0  # the index of its first frame buffer: SOEM's is 0
    misread: dict[int, int] = {}  # ring position -> scans in which its identity reads 0 (a failed EEPROM read)

    def __init__(self) -> None:
        self.hub: RingHub | None = None
        self.clock: EmulatedClock | None = None
        self.frames: SoemFrames | None = None
        self.slaves: list[FakeSoemSlave] = []
        self.sdo_read_timeout = self.sdo_write_timeout = 700_000
        self.manual_state_change = 0
        self.state = pysoem.NONE_STATE
        self.expected_wkc = 0
        self.errors: list[Exception] = []
        self.dc_time = 0
        self.closed = False
        self._cycle_index: int | None = None
        self._image_out = 0
        FakeSoemMaster.last = self

    def open(self, ifname: str, ifname_red: str | None = None) -> None:
        self.hub, self.clock = FakeSoemMaster.ring[ifname]
        self.frames = SoemFrames(self.hub, self.clock, FakeSoemMaster.index_base)

    def close(self) -> None:
        self.closed = True
        if self.hub is not None and self.hub.cycle is self._carry_cycle:
            self.hub.cycle = None

    # ---- scan -----------------------------------------------------------------------------------------------
    def config_init(self, usetable: bool = False) -> int:
        """ecx_config_init: reset every slave, count them (a broadcast read, EC_TIMEOUTSAFE), address each,
        program its mailbox SyncManagers from the SII and ask for PRE-OP."""
        frames = self.frames
        frames.srconfirm([Request(Command.BWR, 0, 0x0120, data=_U16.pack(0x11))], EC_TIMEOUTRET3)
        replies = frames.srconfirm([Request(Command.BRD, 0, 0x0000, size=1)], EC_TIMEOUTSAFE)
        count = 0 if replies is None else replies[0].wkc
        self.slaves = [FakeSoemSlave(self, k) for k in range(count)]
        for k, slave in enumerate(self.slaves):
            address = Request(Command.APWR, (-k) & 0xFFFF, 0x0010, data=_U16.pack(slave.station))
            frames.srconfirm([address], EC_TIMEOUTRET3)
            out_start, out_size, in_start, in_size = slave.mailbox
            slave._wr(0x0800, struct.pack("<HHBBBB", out_start, out_size, 0x26, 0, 1, 0)
                      + struct.pack("<HHBBBB", in_start, in_size, 0x22, 0, 1, 0), EC_TIMEOUTRET3)
            slave._wr(0x0120, _U16.pack(pysoem.PREOP_STATE | pysoem.STATE_ACK), EC_TIMEOUTRET3)
        return count if count else -1 if replies is None else 0

    def read_state(self) -> int:
        for slave in self.slaves:
            wkc, data = slave._rd(0x0130, 6)
            slave.state = _U16.unpack_from(data)[0] if wkc else pysoem.NONE_STATE
            slave.al_status = _U16.unpack_from(data, 4)[0] if wkc else slave.al_status
        return min((s.state for s in self.slaves), default=0)

    def state_check(self, expected_state: int, timeout: int = 50000) -> int:
        deadline = self.clock() + timeout / 1e6
        while True:
            lowest = self.read_state()
            if lowest == expected_state or self.clock() >= deadline:
                return lowest
            self.clock.sleep(0.001)

    def write_state(self) -> int:
        replies = self.frames.srconfirm([Request(Command.BWR, 0, 0x0120, data=_U16.pack(self.state))], EC_TIMEOUTRET3)
        return 0 if replies is None else replies[0].wkc

    # ---- layout ---------------------------------------------------------------------------------------------
    def config_map(self) -> int:
        """ecx_config_map_group: per slave, PRE-OP, the hook, the mapping read back and the SyncManagers and FMMUs
        sized from it; the hook's exception, or SOEM's errors, raised as pysoem raises them."""
        self.errors = []
        for slave in self.slaves:
            slave.state_check(pysoem.PREOP_STATE, 2_000_000)
            if slave.config_func is not None:
                slave.config_func(slave.position)
            slave.obits, slave.ibits = slave.read_pdo_map()
        n = len(self.slaves)
        out_total = sum((s.obits + 7) // 8 for s in self.slaves)
        log_out, log_in = 0, out_total
        for slave in self.slaves:
            out_bytes, in_bytes = (slave.obits + 7) // 8, (slave.ibits + 7) // 8
            slave.output, slave.input = bytes(out_bytes), bytes(in_bytes)
            outputs_at = max(0x1100, slave.mailbox[0] + 2 * slave.mailbox[1])
            slave._wr(0x0810, struct.pack("<HHBBBB", outputs_at, out_bytes, 0x64, 0, 1 if out_bytes else 0, 0))
            slave._wr(0x0818, struct.pack("<HHBBBB", outputs_at + 0x80, in_bytes, 0x20, 0, 1 if in_bytes else 0, 0))
            slave._wr(0x0600, struct.pack("<IHBBHBBBxxx", log_out, out_bytes, 0, 7, outputs_at, 0, 2, 1))
            slave._wr(0x0610, struct.pack("<IHBBHBBBxxx", log_in, in_bytes, 0, 7, outputs_at + 0x80, 0, 1, 1))
            log_out += out_bytes
            log_in += in_bytes
        self._image_out, self._image_in = out_total, log_in - out_total
        self.expected_wkc = 3 * n
        if self.errors:
            raise pysoem.ConfigMapError(list(self.errors))
        return log_in

    def config_dc(self) -> bool:
        """ecx_configdc: latch the receive times, then set each slave's offset so its system time reads the
        reference clock's (the first slave's)."""
        self.frames.srconfirm([Request(Command.BWR, 0, 0x0900, data=bytes(4))], EC_TIMEOUTRET3)
        reference = None
        for slave in self.slaves:
            _wkc, data = slave._rd(0x0918, 8)
            local = _U64.unpack(data)[0]
            if reference is None:
                reference = local
            slave._wr(0x0920, _U64.pack((reference - local + 700 * slave.position) % (1 << 64)))
            slave._wr(0x0928, _U32.pack(700 * slave.position))
        return True

    # ---- the cycle ------------------------------------------------------------------------------------------
    def _cycle_requests(self) -> list[Request]:
        image = b"".join(s.output for s in self.slaves) + bytes(self._image_in)
        return [Request(Command.LRW, 0, 0, data=image), Request(Command.FRMW, STATION_BASE, 0x0910, data=bytes(8))]

    def send_processdata(self) -> int:
        if self._cycle_index is not None:
            self.frames.release(self._cycle_index)
        self._cycle_index = self.frames.index()
        self.frames.send(self._cycle_index, self._cycle_requests())
        self.hub.cycle = self._carry_cycle
        return 1

    def receive_processdata(self, timeout: int = 2000, release_gil: bool = False) -> int:
        idx, self._cycle_index = self._cycle_index, None
        if idx is None:
            return -1
        frame = self.frames.wait(idx, timeout / 1e6)
        self.frames.release(idx)
        if frame is None:
            return -1
        got = _datagrams(frame)
        if not got or got[0][0] != Command.LRW:
            return -1  # another datagram's frame in this buffer: SOEM counts no Command.LRW in it
        _command, image, wkc = got[0]
        at = self._image_out
        for slave in self.slaves:
            slave.input = image[at:at + len(slave.input)]
            at += len(slave.input)
        if len(got) > 1 and got[1][0] == Command.FRMW:
            self.dc_time = _U64.unpack(got[1][1])[0]
        return wkc

    def _carry_cycle(self) -> None:
        """The cycle, on its own, while emulated time passes with nobody sending one (the keeper's part)."""
        frame = bytearray(build_frame(0x3F, self._cycle_requests()))
        self.hub.ring.process(frame, round(self.clock.now * 1e9))
        self.hub.ring.finish_frame()
