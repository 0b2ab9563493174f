"""One EtherCAT slave controller (ESC): register space, SyncManagers (mailboxes among them) and FMMUs, as the master
sees them over the wire; its SII EEPROM interface and its distributed clock are parts of their own.

Register facts relied on (ETG.1000.4, Beckhoff ESC datasheet section II; read the same way by SOEM):

- 0x0000-0x000F ESC information (0x0008 features: bit 2 DC supported, SOEM's ``hasdc``); 0x0010
  configured station address (set by APWR during ec_config_init); 0x0012 alias (SII word 4);
  0x0110 DL status (bit 9 communication on port 0, bit 11 on port 1, bit 10 port 1 loop closed);
  0x0120 AL control (bits 0-3 requested state, bit 4 error acknowledge); 0x0130 AL status (bits 0-3
  state, bit 4 error); 0x0134 AL status code; 0x0140 PDI control.
- 0x0400 watchdog divider and 0x0420 SyncManager watchdog time: the output watchdog runs out after
  ``(divider + 2) * 40 ns * time`` without a write to an SM with bit 6 (watchdog trigger) in its
  control byte; the defaults 2498 and 1000 give 100 ms. 0 disables it.
- 0x0500-0x050F the SII EEPROM interface (``eeprom.py``).
- FMMU n at 0x0600 + 16n: logical start u32, length u16, start bit, end bit, physical start u16,
  physical start bit, type (bit 0 read, bit 1 write), active. Mapping is byte-granular here; SOEM maps
  byte-oriented slaves with start bit 0 and end bit 7.
- SyncManager n at 0x0800 + 8n: start u16, length u16, control (bits 0-1: 00 buffered, 10 mailbox;
  bits 2-3: 00 ECAT reads, 01 ECAT writes; bit 6 watchdog trigger), status (bit 3 mailbox full; read
  only), activate (bit 0 enable, bit 1 repeat request), PDI control (bit 0 deactivated by the slave,
  bit 1 repeat acknowledge; read only). A write mailbox accepts a write only while empty and becomes
  full when its last byte is written, until the slave takes the request out; a read mailbox answers
  only while full and empties when its last byte is read; a refused access does not count in the
  working counter. An SM the slave deactivated refuses all access (that is how SAFE-OP keeps outputs
  out of the working counter).
- 0x0900-0x09A7 the distributed clock (``dc.py``).
"""

from __future__ import annotations

import struct
from typing import Protocol

from humanoid_prime.drivers.ethercat.wire import (
    AL_ERROR,
    FMMU_LAYOUT,
    FMMU_READ,
    FMMU_SIZE,
    FMMU_WRITE,
    REG_AL_CONTROL,
    REG_AL_STATUS,
    REG_AL_STATUS_CODE,
    REG_ALIAS,
    REG_DC_RECEIVE_TIME,
    REG_DC_SYSTEM_TIME,
    REG_DL_STATUS,
    REG_EEPROM_CONTROL,
    REG_FMMU,
    REG_PDI_CONTROL,
    REG_SM,
    REG_STATION_ADDRESS,
    REG_WD_DIVIDER,
    REG_WD_SM_TIME,
    REG_WD_STATUS,
    SII_WORD_ALIAS,
    SM_DIRECTION_WRITE,
    SM_ENABLE,
    SM_LAYOUT,
    SM_MODE_MAILBOX,
    SM_MODE_MASK,
    SM_PDI_DEACTIVATED,
    SM_SIZE,
    SM_STATUS_MAILBOX_FULL,
    SM_WATCHDOG_TRIGGER,
    AlState,
    Command,
)
from humanoid_prime.virtual.ring.dc import EscClock
from humanoid_prime.virtual.ring.eeprom import SiiEeprom

MEMORY_SIZE = 0x3000  # 4 KiB registers + 8 KiB process RAM
PROCESS_RAM = 0x1000
SM_COUNT = 8
FMMU_COUNT = 8
_U16 = struct.Struct("<H")

# Bytes the master may write; everything else in 0x0000-0x0FFF is read only for EtherCAT.
_WRITABLE_RANGES = (
    (0x0010, 0x0012), (0x0100, 0x0104), (0x0108, 0x010A), (0x0120, 0x0122), (0x0200, 0x0202),
    (0x0300, 0x0314), (0x0400, 0x0402), (0x0410, 0x0412), (0x0420, 0x0422), (0x0442, 0x0444),
    (0x0500, 0x0501), (0x0502, 0x0510), (0x0600, 0x0700), (0x0800, 0x0880), (0x0900, 0x0904),
    (0x0910, 0x0918), (0x0920, 0x092C), (0x0930, 0x0932), (0x0934, 0x0936), (0x0980, 0x0982),
    (0x0990, 0x0998), (0x09A0, 0x09A8),
)


class EscApplication(Protocol):
    """What a slave's firmware (the PDI side) is told by its ESC."""

    def al_control(self, value: int) -> None: ...
    def mailbox_received(self, message: bytes) -> bool: ...
    def mailbox_read(self) -> None: ...
    def mailbox_changed(self) -> None: ...
    def outputs_written(self) -> None: ...
    def sync_activation_changed(self) -> None: ...


class Esc:
    """Register memory and ESC mechanics of one slave. ``frame_time_ns`` (monotonic ns of the frame being
    processed) is set by the ring before each frame; ``clock`` is its distributed clock, ``eeprom`` its SII."""

    def __init__(self, sii: bytes, app: EscApplication, *, clock_origin_ns: int, eeprom_busy_s: float = 0.0) -> None:
        self.mem = bytearray(MEMORY_SIZE)
        self.app = app
        self.frame_time_ns = clock_origin_ns
        self.clock = EscClock(self.mem, lambda: self.frame_time_ns, app.sync_activation_changed,
                              origin_ns=clock_origin_ns)
        self.eeprom = SiiEeprom(sii, self.mem, busy_s=eeprom_busy_s)
        self.last_output_write_ns: int | None = None
        self.output_watchdog_ns = 0  # SM watchdog period; 0 = disabled
        self._writable = bytearray(0x1000)
        for start, end in _WRITABLE_RANGES:
            self._writable[start:end] = b"\x01" * (end - start)
        for n in range(SM_COUNT):
            self._writable[REG_SM + SM_SIZE * n + 5] = 0
            self._writable[REG_SM + SM_SIZE * n + 7] = 0
        self._writable[REG_DC_SYSTEM_TIME:REG_DC_SYSTEM_TIME + 8] = bytes(8)  # a write there is a time sample
        self._sms: list[tuple[int, int, int, int, int]] = []  # (index, start, end, control, pdi_disabled)
        self._fmmus: list[tuple[int, int, int, int]] = []  # (logical start, logical end, physical, type)
        self._last_mailbox_reply = b""
        self.power_on()

    # ---- power-on values ------------------------------------------------------------------------------
    def power_on(self, now_ns: int | None = None) -> None:
        """Registers as after power-up: INIT, no station address, SMs, FMMUs and the DC offset cleared; the local
        clock starts again from 0 at ``now_ns`` (when given)."""
        mem = self.mem
        mem[:] = bytes(MEMORY_SIZE)
        # type, revision, build, FMMUs, SyncManagers, RAM (KiB), port descriptor, features (bit 2: DC)
        struct.pack_into("<BBHBBBBH", mem, 0, 0x11, 0x00, 0x0002, FMMU_COUNT, SM_COUNT, 8, 0x0F, 0x01FC)
        image = self.eeprom.image
        _U16.pack_into(mem, REG_ALIAS, _U16.unpack_from(image, 2 * SII_WORD_ALIAS)[0])
        mem[REG_PDI_CONTROL] = image[0]
        _U16.pack_into(mem, REG_AL_STATUS, AlState.INIT)
        _U16.pack_into(mem, REG_WD_DIVIDER, 2498)  # with 1000 in 0x0420: a 100 ms output watchdog
        _U16.pack_into(mem, REG_WD_SM_TIME, 1000)
        _U16.pack_into(mem, REG_WD_STATUS, 0x0001)
        self.eeprom.power_on()
        self.clock.power_on(now_ns)
        self.last_output_write_ns = None
        self._last_mailbox_reply = b""
        self._update_watchdog()
        self._rebuild_sms()
        self._rebuild_fmmus()

    def set_links(self, port1_open: bool) -> None:
        """DL status for a line: port 0 towards the master, port 1 open when a slave follows."""
        status = 0x0010 | 0x0200 | (0x0020 | 0x0800 if port1_open else 0x0400)
        _U16.pack_into(self.mem, REG_DL_STATUS, status)

    # ---- identity -------------------------------------------------------------------------------------
    @property
    def station_address(self) -> int:
        return _U16.unpack_from(self.mem, REG_STATION_ADDRESS)[0]

    # ---- AL registers, written by the firmware --------------------------------------------------------
    @property
    def al_control_value(self) -> int:
        return _U16.unpack_from(self.mem, REG_AL_CONTROL)[0]

    @property
    def al_status(self) -> int:
        return _U16.unpack_from(self.mem, REG_AL_STATUS)[0]

    @property
    def al_status_code(self) -> int:
        return _U16.unpack_from(self.mem, REG_AL_STATUS_CODE)[0]

    def set_al_status(self, state: int, error: bool, code: int) -> None:
        _U16.pack_into(self.mem, REG_AL_STATUS, state | (AL_ERROR if error else 0))
        _U16.pack_into(self.mem, REG_AL_STATUS_CODE, code)

    # ---- SyncManagers -----------------------------------------------------------------------------------
    def sync_manager(self, n: int) -> tuple[int, int, int, int]:
        """(start, length, control, activate) as the master programmed SM ``n``."""
        start, length, control, _status, activate, _pdi = SM_LAYOUT.unpack_from(self.mem, REG_SM + SM_SIZE * n)
        return start, length, control, activate

    def set_sm_deactivated(self, n: int, deactivated: bool) -> None:
        """The slave (PDI) deactivates or re-enables SM ``n``."""
        address = REG_SM + SM_SIZE * n + 7
        self.mem[address] = (self.mem[address] & ~SM_PDI_DEACTIVATED & 0xFF) | int(deactivated)
        self._rebuild_sms()

    def _rebuild_sms(self) -> None:
        sms = []
        for n in range(SM_COUNT):
            start, length, control, _status, activate, pdi = SM_LAYOUT.unpack_from(self.mem, REG_SM + SM_SIZE * n)
            if activate & SM_ENABLE and length:
                sms.append((n, start, start + length, control, pdi & SM_PDI_DEACTIVATED))
        self._sms = sms

    def _mailbox_full(self, n: int) -> bool:
        return bool(self.mem[REG_SM + SM_SIZE * n + 5] & SM_STATUS_MAILBOX_FULL)

    def _set_mailbox_full(self, n: int, full: bool) -> None:
        address = REG_SM + SM_SIZE * n + 5
        self.mem[address] = (self.mem[address] & ~SM_STATUS_MAILBOX_FULL & 0xFF) | (SM_STATUS_MAILBOX_FULL * full)

    def _mailbox_sm(self, direction_write: bool) -> tuple[int, int, int, int, int] | None:
        for sm in self._sms:
            control = sm[3]
            if control & SM_MODE_MASK == SM_MODE_MAILBOX and bool(control & SM_DIRECTION_WRITE) == direction_write:
                return sm
        return None

    def post_mailbox(self, message: bytes) -> bool:
        """Put a reply into the read mailbox; False if it is still full or not configured."""
        sm = self._mailbox_sm(direction_write=False)
        if sm is None or self._mailbox_full(sm[0]):
            return False
        n, start, end = sm[0], sm[1], sm[2]
        body = message[:end - start]
        self.mem[start:start + len(body)] = body
        self.mem[start + len(body):end] = bytes(end - start - len(body))
        self._last_mailbox_reply = bytes(self.mem[start:end])
        self._set_mailbox_full(n, True)
        return True

    def take_mailbox_request(self) -> bytes | None:
        """The request waiting in the full write mailbox, which the slave takes out (None if empty)."""
        sm = self._mailbox_sm(direction_write=True)
        if sm is None or not self._mailbox_full(sm[0]):
            return None
        self._set_mailbox_full(sm[0], False)
        return bytes(self.mem[sm[1]:sm[2]])

    @property
    def reply_mailbox_full(self) -> bool:
        sm = self._mailbox_sm(direction_write=False)
        return sm is not None and self._mailbox_full(sm[0])

    def clear_mailboxes(self) -> None:
        """Empty both mailboxes and forget the last reply (the slave went back to INIT): nothing of one master
        session is ever offered to the next."""
        for sm in self._sms:
            if sm[3] & SM_MODE_MASK == SM_MODE_MAILBOX:
                self._set_mailbox_full(sm[0], False)
        self._forget_reply()

    def _forget_reply(self) -> None:
        """No reply to repeat, and the repeat handshake back in step with whatever the master asks next."""
        self._last_mailbox_reply = b""
        for n in range(SM_COUNT):
            _start, _length, control, activate = self.sync_manager(n)
            if control & SM_MODE_MASK == SM_MODE_MAILBOX and not control & SM_DIRECTION_WRITE:
                ack = REG_SM + 8 * n + 7
                self.mem[ack] = (self.mem[ack] & ~0x02 & 0xFF) | (activate & 0x02)

    def _repeat_request(self, n: int) -> None:
        """Master toggled the repeat request of the read mailbox: offer the last reply again."""
        start, length, _control, activate = self.sync_manager(n)
        ack = REG_SM + 8 * n + 7
        if bool(activate & 0x02) == bool(self.mem[ack] & 0x02):
            return
        if self._last_mailbox_reply:
            self.mem[start:start + length] = self._last_mailbox_reply[:length]
            self._set_mailbox_full(n, True)
        self.mem[ack] ^= 0x02

    # ---- FMMUs ------------------------------------------------------------------------------------------
    def _rebuild_fmmus(self) -> None:
        fmmus = []
        for n in range(FMMU_COUNT):
            address = REG_FMMU + FMMU_SIZE * n
            log_start, length, _sb, _eb, phys, _pb, kind, active = FMMU_LAYOUT.unpack_from(self.mem, address)
            if active & 0x01 and length and kind & (FMMU_READ | FMMU_WRITE):
                fmmus.append((log_start, log_start + length, phys, kind & (FMMU_READ | FMMU_WRITE)))
        self._fmmus = fmmus

    # ---- watchdog ---------------------------------------------------------------------------------------
    def _update_watchdog(self) -> None:
        divider = _U16.unpack_from(self.mem, REG_WD_DIVIDER)[0]
        self.output_watchdog_ns = (divider + 2) * 40 * _U16.unpack_from(self.mem, REG_WD_SM_TIME)[0]

    # ---- physical access (APxx, FPxx, Bxx, xRMW) ------------------------------------------------------------
    def read(self, address: int, frame: bytearray, offset: int, length: int, combine: bool = False) -> bool:
        """Copy ``length`` bytes at ``address`` into ``frame[offset:]`` (OR-ed in when ``combine``, as for
        broadcast reads). False when the ESC refuses (empty read mailbox, deactivated SM)."""
        end = address + length
        self.clock.before_read(address, end)
        if address < REG_EEPROM_CONTROL + 0x0E and end > REG_EEPROM_CONTROL:
            self.eeprom.before_read(self.frame_time_ns)
        emptied = None
        if end > PROCESS_RAM:
            for n, start, sm_end, control, pdi_disabled in self._sms:
                if address < sm_end and end > start:
                    if pdi_disabled:
                        return False
                    if control & SM_MODE_MASK == SM_MODE_MAILBOX and not control & SM_DIRECTION_WRITE:
                        if not self._mailbox_full(n):
                            return False
                        if address < sm_end <= end:
                            emptied = n
        top = min(end, MEMORY_SIZE)
        if combine:
            for i in range(address, top):
                frame[offset + i - address] |= self.mem[i]
        elif top > address:
            frame[offset:offset + top - address] = self.mem[address:top]
        if emptied is not None:
            self._set_mailbox_full(emptied, False)
            self.app.mailbox_read()
        return True

    def write(self, address: int, frame: bytearray | bytes, offset: int, length: int) -> bool:
        """Copy ``frame[offset:offset+length]`` to ``address`` with the ESC's side effects; False when
        refused (full write mailbox, wrong direction, deactivated SM)."""
        end = address + length
        data = frame[offset:offset + length]
        if address < PROCESS_RAM:
            self._write_registers(address, data)
        if end <= PROCESS_RAM:
            return True
        ram_start = max(address, PROCESS_RAM)
        ram_data = data[ram_start - address:]
        filled = None
        for n, start, sm_end, control, pdi_disabled in self._sms:
            if ram_start < sm_end and end > start:
                if pdi_disabled or not control & SM_DIRECTION_WRITE:
                    return False
                if control & SM_MODE_MASK == SM_MODE_MAILBOX:
                    if self._mailbox_full(n):
                        return False
                    if ram_start < sm_end <= end:
                        filled = (n, start, sm_end)
        top = min(end, MEMORY_SIZE)
        self.mem[ram_start:top] = ram_data[:top - ram_start]
        if filled is not None:
            n, start, sm_end = filled
            self._set_mailbox_full(n, True)
            if self.app.mailbox_received(bytes(self.mem[start:sm_end])):
                self._set_mailbox_full(n, False)  # the firmware took the request out at once
        return True

    def _write_registers(self, address: int, data: bytes | bytearray) -> None:
        end = min(address + len(data), PROCESS_RAM)
        data = data[:end - address]
        if self.clock.time_distribution(address, data):  # every cycle: the register keeps the local copy
            return
        mem = self.mem
        writable = self._writable
        for i in range(address, end):
            if writable[i]:
                mem[i] = data[i - address]
        touched = (address, end)
        if _overlaps(touched, REG_AL_CONTROL, 2):
            self.app.al_control(self.al_control_value)
        if _overlaps(touched, REG_WD_DIVIDER, 0x22):
            self._update_watchdog()
        if _overlaps(touched, REG_EEPROM_CONTROL, 2):
            self.eeprom.command_written(self.frame_time_ns)
        if _overlaps(touched, REG_FMMU, FMMU_SIZE * FMMU_COUNT):
            self._rebuild_fmmus()
        if _overlaps(touched, REG_SM, SM_SIZE * SM_COUNT):
            self._sync_managers_written(touched)
        if _overlaps(touched, REG_DC_RECEIVE_TIME, 0xA8):
            self.clock.written(address, data)

    def _sync_managers_written(self, touched: tuple[int, int]) -> None:
        enabled_before = {sm[0] for sm in self._sms}
        self._rebuild_sms()
        for n in range(SM_COUNT):
            if _overlaps(touched, REG_SM + SM_SIZE * n + 6, 1):
                _start, _length, control, activate = self.sync_manager(n)
                read_mailbox = control & SM_MODE_MASK == SM_MODE_MAILBOX and not control & SM_DIRECTION_WRITE
                if not activate & SM_ENABLE:
                    self._set_mailbox_full(n, False)
                    if read_mailbox:
                        self._forget_reply()
                elif read_mailbox and n not in enabled_before:
                    self._forget_reply()  # a fresh configuration, not a repeat request
                elif read_mailbox:
                    self._repeat_request(n)
        if _overlaps(touched, REG_SM, 2 * SM_SIZE):  # SM0/SM1, the mailboxes the SII describes
            self.app.mailbox_changed()

    # ---- logical access (LRD, LWR, LRW) -------------------------------------------------------------------
    def logical(self, command: int, address: int, frame: bytearray, offset: int, length: int) -> int:
        """Serve a logical datagram through the FMMUs; returns this slave's working-counter increment:
        LRD +1 if read, LWR +1 if written, LRW +1 read and +2 written."""
        end = address + length
        did_read = did_write = False
        for log_start, log_end, phys, kind in self._fmmus:
            lo = address if address > log_start else log_start
            hi = end if end < log_end else log_end
            if lo >= hi:
                continue
            p = phys + lo - log_start
            f = offset + lo - address
            n = hi - lo
            if kind & 0x01 and command != Command.LWR and self._process_access(p, n, write=False):
                frame[f:f + n] = self.mem[p:p + n]
                did_read = True
            if kind & 0x02 and command != Command.LRD and self._process_access(p, n, write=True):
                self.mem[p:p + n] = frame[f:f + n]
                did_write = True
                for _n, _start, sm_end, control, _pdi in self._sms:
                    if p < sm_end <= p + n:
                        if control & SM_WATCHDOG_TRIGGER:
                            self.last_output_write_ns = self.frame_time_ns
                        self.app.outputs_written()
        if command == Command.LRW:
            return did_read + 2 * did_write
        return int(did_read or did_write)

    def _process_access(self, address: int, length: int, write: bool) -> bool:
        end = address + length
        if end > MEMORY_SIZE:
            return False
        for _n, start, sm_end, control, pdi_disabled in self._sms:
            if address < sm_end and end > start:
                if pdi_disabled or control & SM_MODE_MASK == SM_MODE_MAILBOX:
                    return False
                if bool(control & SM_DIRECTION_WRITE) != write:
                    return False
        return True


def _overlaps(span: tuple[int, int], start: int, length: int) -> bool:
    return span[0] < start + length and span[1] > start
