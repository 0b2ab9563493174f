"""A minimal in-process master for ring tests: builds SOEM-shaped frames, passes them through a Ring and
reads the replies. It configures slaves the way ec_config_init / ec_config_map / ec_configdc do, without
a network."""

from __future__ import annotations

import struct

from humanoid_prime.drivers.erob.objects import MAPPING_WRITES, RXPDO_STRUCT, TXPDO_STRUCT
from humanoid_prime.drivers.ethercat.wire import Command, mailbox_message
from humanoid_prime.virtual.ring.frames import Datagram, build_frame, parse_frame
from humanoid_prime.virtual.ring.ring import Ring

STATION_BASE = 0x1001
MAILBOX_OUT = 0x1000
MAILBOX_IN = 0x1080
OUTPUTS = 0x1100
INPUTS = 0x1180
DC_TIME = 0x0910
RING_TIME_NS = 816_000_000_000_000_000  # a system time in 2025 (ns since 2000, the DC epoch)


class WireMaster:
    """Talks to ``ring`` with frames; ``now_ns`` is advanced by the caller (or by ``cycle``)."""

    def __init__(self, ring: Ring, now_ns: int) -> None:
        self.ring = ring
        self.now_ns = now_ns
        self.counter = 0

    def exchange(self, datagrams: list[Datagram]) -> list[Datagram]:
        frame = bytearray(build_frame(datagrams))
        assert self.ring.process(frame, self.now_ns)
        self.ring.finish_frame()
        return parse_frame(frame)

    def one(self, datagram: Datagram) -> Datagram:
        return self.exchange([datagram])[0]

    def aprd(self, position: int, ado: int, length: int) -> Datagram:
        return self.one(Datagram(Command.APRD, bytes(length), adp=(-position) & 0xFFFF, ado=ado))

    def apwr(self, position: int, ado: int, data: bytes) -> Datagram:
        return self.one(Datagram(Command.APWR, data, adp=(-position) & 0xFFFF, ado=ado))

    def fprd(self, station: int, ado: int, length: int) -> Datagram:
        return self.one(Datagram(Command.FPRD, bytes(length), adp=station, ado=ado))

    def fpwr(self, station: int, ado: int, data: bytes) -> Datagram:
        return self.one(Datagram(Command.FPWR, data, adp=station, ado=ado))

    def brd(self, ado: int, length: int) -> Datagram:
        return self.one(Datagram(Command.BRD, bytes(length), ado=ado))

    def bwr(self, ado: int, data: bytes) -> Datagram:
        return self.one(Datagram(Command.BWR, data, ado=ado))

    # ---- configuration as SOEM does it --------------------------------------------------------------------
    def set_station_addresses(self) -> None:
        for i in range(len(self.ring.reachable)):
            self.apwr(i, 0x0010, struct.pack("<H", STATION_BASE + i))

    def request_state(self, station: int, state: int) -> None:
        self.fpwr(station, 0x0120, struct.pack("<H", state))

    def al_status(self, station: int) -> tuple[int, int]:
        data = self.fprd(station, 0x0130, 6).data
        return struct.unpack_from("<H", data)[0], struct.unpack_from("<H", data, 4)[0]

    def program_mailbox(self, station: int, size: int = 128) -> None:
        self.fpwr(station, 0x0800, struct.pack("<HHI", MAILBOX_OUT, size, 0x00010026)
                  + struct.pack("<HHI", MAILBOX_IN, size, 0x00010022))

    def program_process_data(self, position: int) -> None:
        """SM2/SM3 and two FMMUs: outputs at logical 13*position, inputs after all outputs."""
        station = STATION_BASE + position
        n = len(self.ring.reachable)
        self.fpwr(station, 0x0810, struct.pack("<HHI", OUTPUTS, RXPDO_STRUCT.size, 0x00010064))
        self.fpwr(station, 0x0818, struct.pack("<HHI", INPUTS, TXPDO_STRUCT.size, 0x00010020))
        out_log = RXPDO_STRUCT.size * position
        in_log = RXPDO_STRUCT.size * n + TXPDO_STRUCT.size * position
        self.fpwr(station, 0x0600, struct.pack("<IHBBHBBBxxx", out_log, RXPDO_STRUCT.size, 0, 7, OUTPUTS, 0, 2, 1))
        self.fpwr(station, 0x0610, struct.pack("<IHBBHBBBxxx", in_log, TXPDO_STRUCT.size, 0, 7, INPUTS, 0, 1, 1))

    def map_pdos(self, station: int) -> None:
        """Prime's PDO mapping over SDO, in PRE-OP (the drive powers up with ZeroErr's own)."""
        for index, sub, data in MAPPING_WRITES:
            reply = self.sdo_download(station, index, sub, data)
            assert reply[8] == 0x60, f"0x{index:04X}:{sub:02X} refused: {reply[6:16].hex()}"  # download response

    def set_clocks(self, master_time_ns: int = RING_TIME_NS) -> None:
        """SOEM's ``ecx_configdc`` without the delays: latch every slave's receive time in one frame, then set each
        offset so that its system time read ``master_time_ns`` then."""
        self.bwr(0x0900, bytes(4))
        for i in range(len(self.ring.reachable)):
            self.set_clock(STATION_BASE + i, master_time_ns)

    def set_clock(self, station: int, master_time_ns: int = RING_TIME_NS) -> None:
        local = struct.unpack("<Q", self.fprd(station, 0x0918, 8).data)[0]
        self.fpwr(station, 0x0920, struct.pack("<Q", (master_time_ns - local) % (1 << 64)))

    def bring_to_safeop(self, map_pdos: bool = True) -> None:
        self.set_station_addresses()
        self.set_clocks()
        for i in range(len(self.ring.reachable)):
            station = STATION_BASE + i
            self.program_mailbox(station)
            self.request_state(station, 0x12)
            if map_pdos:
                self.map_pdos(station)
            self.program_process_data(i)
            self.request_state(station, 0x04)

    def start_sync0(self, station: int, cycle_ns: int, delay_ns: int = 1_000_000) -> None:
        system = struct.unpack("<Q", self.fprd(station, DC_TIME, 8).data)[0]
        self.fpwr(station, 0x0981, b"\x00")
        self.fpwr(station, 0x0990, struct.pack("<Q", system + delay_ns))
        self.fpwr(station, 0x09A0, struct.pack("<I", cycle_ns))
        self.fpwr(station, 0x0981, b"\x03")

    # ---- process data -------------------------------------------------------------------------------------
    def cycle(self, outputs: list[bytes], period_ns: int, distribute_time: bool = True) -> tuple[int, list[bytes]]:
        """One LRW (+ FRMW on 0x0910) after advancing the clock by ``period_ns``; (wkc, inputs per slave)."""
        self.now_ns += period_ns
        self.ring.advance(self.now_ns)
        n = len(outputs)
        image = b"".join(outputs) + bytes(TXPDO_STRUCT.size * n)
        datagrams = [Datagram.logical(Command.LRW, 0, image)]
        if distribute_time:
            datagrams.append(Datagram(Command.FRMW, bytes(8), adp=STATION_BASE, ado=DC_TIME))
        reply = self.exchange(datagrams)[0]
        base = RXPDO_STRUCT.size * n
        inputs = [reply.data[base + TXPDO_STRUCT.size * i: base + TXPDO_STRUCT.size * (i + 1)] for i in range(n)]
        return reply.wkc, inputs

    # ---- mailbox ------------------------------------------------------------------------------------------
    def mailbox_write(self, station: int, payload: bytes, size: int = 128) -> Datagram:
        self.counter = self.counter % 7 + 1
        message = mailbox_message(payload, 3, self.counter)
        return self.fpwr(station, MAILBOX_OUT, message + bytes(size - len(message)))

    def mailbox_read(self, station: int, size: int = 128) -> bytes | None:
        status = self.fprd(station, 0x080D, 1).data[0]
        if not status & 0x08:
            return None
        return self.fprd(station, MAILBOX_IN, size).data

    def sdo_download(self, station: int, index: int, sub: int, data: bytes) -> bytes:
        """An expedited download; the reply message."""
        command = 0x23 | ((4 - len(data)) << 2)
        return self.sdo_request(station, struct.pack("<HBHB", 0x2000, command, index, sub) + data.ljust(4, b"\x00"))

    def sdo_upload(self, station: int, index: int, sub: int) -> bytes:
        """An expedited upload; the object's bytes (asserts the drive answered with data, not an abort)."""
        reply = self.sdo_request(station, struct.pack("<HBHB4x", 0x2000, 0x40, index, sub))
        command = reply[8]
        assert command & 0xE3 == 0x43, f"0x{index:04X}:{sub:02X} not an expedited upload reply: {reply[6:16].hex()}"
        return reply[12:16 - ((command >> 2) & 3)]

    def sdo_request(self, station: int, payload: bytes) -> bytes:
        """One CoE request; the reply message, waited for one emulated millisecond at a time."""
        self.mailbox_write(station, payload)
        for _ in range(100):
            reply = self.mailbox_read(station)
            if reply is not None:
                return reply
            self.now_ns += 1_000_000
            self.ring.advance(self.now_ns)
        raise AssertionError(f"no SDO reply from station 0x{station:04X} in 100 emulated ms")
