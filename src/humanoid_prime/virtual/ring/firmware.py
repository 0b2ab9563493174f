"""The application side of one emulated eRob slave: AL state machine, CoE mailbox with latency, process
data to and from the drive, output watchdog, and the DC lock and SYNC0 supervision.

AL state machine (ETG.1000.6): INIT -> PRE-OP needs the mailbox SyncManagers as the SII describes them
(else 0x0016); PRE-OP -> SAFE-OP needs SM2/SM3 matching the PDO mapping in 0x1C12/0x1C13 (else
0x001D/0x001E); SAFE-OP -> OP is described below; skipping a state is refused with 0x0011, BOOT with
0x0013. With the error flag set, only requests to a lower state are served until the master writes
the acknowledge bit. Outputs (SM2) count in the working counter only in OP, inputs (SM3) in SAFE-OP and
OP: the slave deactivates the SyncManager otherwise.

DC model. SYNC0 runs once 0x0981 = 3 and the system time has reached the start time 0x0990 (a start
time already past at activation never starts, as on a real ESC). A slave locks after ``dc_lock_cycles``
process-data frames that also carry the master's time distribution (the FRMW/ARMW on 0x0910), each no
more than ``SYNC0 cycle * (1 + sync_tolerance)`` after the previous one; a longer gap (SYNC0 faster
than the frames) restarts the count, so a SYNC0 faster than the frame rate never locks. So does a frame
whose time distribution finds the slave's system time more than ``dc_sync_window_ns`` off the reference
clock's (0x092C): SYNC0 runs on the slave's own copy of the ring's time, and a copy that far off (a slave
back from a power cycle whose offset the master did not set again, or a ring whose reference clock
started again from 0) puts SYNC0 out of step with the frames. A locked slave in SAFE-OP loses its lock on
such a frame. SAFE-OP -> OP waits, without error, until the slave has locked (a pending OP request
completes then). In OP, ``sync_fault_cycles`` consecutive gaps longer than that, or frames that far off,
fault the drive (0xA000) and drop the slave to SAFE-OP with AL code 0x001A. In OP with SYNC0 not running,
a drive enabled in CSP faults at once (0xA000): CSP needs DC. A mailbox request while SYNC0 is on but not
yet locked (the activation phase) faults the drive with 0xA000 and restarts the lock. A SYNC0 cycle below
500 us is refused at SAFE-OP -> OP (0x0035).

Watchdog: in OP, no output write for the ESC's SM watchdog time (100 ms by default) -> SAFE-OP with AL
code 0x001B. Leaving OP while the drive is enabled faults it with 0xA000.

Mailbox SyncManagers: a master that switches SM0 or SM1 off, or moves them, in PRE-OP or above drops the slave
to INIT with AL code 0x0016 (invalid mailbox configuration), as Beckhoff's slave stack does on the SM change
event; its reply mailbox is gone until the master configures it again. How long replies take is the ring's
``MailboxLatency``.
"""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Callable
from enum import IntEnum

from humanoid_prime.drivers.erob import objects as obj
from humanoid_prime.drivers.erob.constants import MIN_CYCLE_S, PRODUCT_CODE, VENDOR_ID
from humanoid_prime.virtual.ring import sii
from humanoid_prime.virtual.ring.drive import ERROR_COMMUNICATION, REVISION, ErobDrive
from humanoid_prime.virtual.ring.esc import Esc
from humanoid_prime.virtual.ring.latency import MailboxLatency
from humanoid_prime.virtual.ring.mailbox import CoeServer
from humanoid_prime.virtual.ring.od import (
    ABORT_DEVICE_STATE,
    ABORT_NOT_MAPPABLE,
    ABORT_PDO_LENGTH,
    ABORT_SUBINDEX_ZERO_FIRST,
    Entry,
    SdoAbort,
)
from humanoid_prime.virtual.ring.options import RingOptions


class AlState(IntEnum):
    INIT = 1
    PREOP = 2
    BOOT = 3
    SAFEOP = 4
    OP = 8


AL_OK = 0x0000
AL_INVALID_STATE_CHANGE = 0x0011
AL_UNKNOWN_STATE = 0x0012
AL_BOOTSTRAP_NOT_SUPPORTED = 0x0013
AL_INVALID_MAILBOX_CONFIG = 0x0016
AL_SYNC_ERROR = 0x001A
AL_WATCHDOG = 0x001B
AL_INVALID_OUTPUT_CONFIG = 0x001D
AL_INVALID_INPUT_CONFIG = 0x001E
AL_INVALID_SYNC_CYCLE = 0x0035

MAILBOX_OUT_START = 0x1000
MAILBOX_IN_START = 0x1080
OUTPUTS_START = 0x1100
INPUTS_START = 0x1180
SM_OUTPUTS = 2
SM_INPUTS = 3
MAX_PDO_BYTES = 0x80

# A write the slave logged: (monotonic s, ring position, index, subindex, raw value, applied).
SdoLogSink = Callable[[float, int, int, int, int, bool], None]


def sii_content(options: RingOptions, serial: int) -> sii.SiiContent:
    size = options.mailbox_size
    return sii.SiiContent(
        vendor_id=VENDOR_ID, product_code=PRODUCT_CODE, revision=REVISION, serial=serial,
        name="eRob CiA402 (emulated)", group="Servo drives", order="eRob70",
        sync_managers=(
            sii.SyncManagerLayout(MAILBOX_OUT_START, size, 0x26, sii.SM_TYPE_MAILBOX_OUT),
            sii.SyncManagerLayout(MAILBOX_IN_START if size <= 0x80 else MAILBOX_OUT_START + size, size, 0x22,
                                  sii.SM_TYPE_MAILBOX_IN),
            sii.SyncManagerLayout(_outputs_start(size), _size(obj.POWER_UP_RXPDO), 0x64, sii.SM_TYPE_OUTPUTS),
            sii.SyncManagerLayout(_outputs_start(size) + MAX_PDO_BYTES, _size(obj.POWER_UP_TXPDO), 0x20,
                                  sii.SM_TYPE_INPUTS),
        ),
        rx_pdo_index=obj.RXPDO_MAP, rx_pdo=obj.POWER_UP_RXPDO, tx_pdo_index=obj.TXPDO_MAP, tx_pdo=obj.POWER_UP_TXPDO,
    )


def _size(entries: tuple[obj.PdoEntry, ...]) -> int:
    return sum(entry.bits for entry in entries) // 8


def _outputs_start(mailbox_size: int) -> int:
    return max(OUTPUTS_START, MAILBOX_OUT_START + 2 * mailbox_size)


class PdoCodec:
    """Packs or unpacks one direction of process data between SM memory and OD entries."""

    def __init__(self, entries: list[Entry | None], paddings: list[int]) -> None:
        fmt = "<"
        self.entries: list[Entry] = []
        for entry, pad in zip(entries, paddings, strict=True):
            if entry is None:
                fmt += "x" * pad
            else:
                fmt += entry.fmt
                self.entries.append(entry)
        self.struct = struct.Struct(fmt)

    @property
    def size(self) -> int:
        return self.struct.size

    def unpack(self, memory: bytearray, address: int) -> None:
        for entry, value in zip(self.entries, self.struct.unpack_from(memory, address), strict=True):
            entry.value = value

    def pack(self, memory: bytearray, address: int) -> None:
        self.struct.pack_into(memory, address, *[e.value for e in self.entries])


class ErobFirmware:
    """Glue between one ESC and one drive model. ``tick(now)`` runs the time-driven parts."""

    def __init__(self, position: int, options: RingOptions, *, clock_origin_ns: int,
                 log: SdoLogSink | None = None, latency: MailboxLatency | None = None) -> None:
        self.position = position
        self.options = options
        self.log = log
        self.latency = latency if latency is not None else MailboxLatency(options)
        serial = 0x00E20000 + position
        self.drive = self._new_drive(serial)
        self.esc = Esc(sii.build_image(sii_content(options, serial)), self, clock_origin_ns=clock_origin_ns)
        self.coe = CoeServer(self.drive.od, options.mailbox_size, on_download=self._downloaded)
        self.state = AlState.INIT
        self.error = False
        self.code = AL_OK
        self.pending_op = False
        self.pending_change: tuple[int, int] | None = None  # (requested state, due ns): options.state_change_s
        self.change_frames: list[int] = []  # per delayed state change, process-data frames the ring carried meanwhile
        self.silent = False
        self.locked = False
        self.lock_count = 0
        self.sync_mismatch = 0
        self.last_cycle_ns: int | None = None
        self.outputs_pending = False
        self.rx: PdoCodec | None = None
        self.tx: PdoCodec | None = None
        self._outputs_at = 0
        self._inputs_at = 0
        self.mailbox_faults = 0
        self.replies_taken = 0  # replies the master read out of the read mailbox (a repeated one counts again)
        self._replies: deque[tuple[int, bytes]] = deque()
        self._guard_pdo_objects()
        self._enter(AlState.INIT)

    # ---- ESC callbacks ------------------------------------------------------------------------------
    def al_control(self, value: int) -> None:
        if self.silent:
            return
        requested = value & 0x0F
        if value & 0x10:
            self.error = False
            self.code = AL_OK
        elif self.error and requested >= self.state:
            return
        if self.pending_change is not None and self.pending_change[0] == requested:
            return  # asked again while it is under way
        self.pending_change = None
        if self.options.state_change_s and requested in (AlState.PREOP, AlState.SAFEOP) and requested > self.state:
            self.pending_change = (requested, self.esc.frame_time_ns + round(self.options.state_change_s * 1e9))
            self.change_frames.append(0)
            return
        self._request(requested)
        self._publish()

    def mailbox_received(self, message: bytes) -> bool:
        if self.silent:
            return False
        now = self.esc.frame_time_ns
        if self.in_dc_activation:
            self.drive.fault(ERROR_COMMUNICATION)
            self.mailbox_faults += 1
            self.locked = False
            self.lock_count = 0
        self._replies.extend((now + self.latency.delay_ns(self.position), reply)  # each posted once SM1 is free
                             for reply in self.coe.handle(message))
        self._post_reply(now)
        return True

    def mailbox_read(self) -> None:
        self.replies_taken += 1
        self._post_reply(self.esc.frame_time_ns)

    def mailbox_changed(self) -> None:
        """The master wrote SM0 or SM1: above INIT, a mailbox switched off or moved drops the slave to INIT."""
        if not self.silent and self.state != AlState.INIT and not self._mailbox_config_ok():
            self._fail(AL_INVALID_MAILBOX_CONFIG, AlState.INIT)

    def outputs_written(self) -> None:
        self.outputs_pending = True

    def sync_activation_changed(self) -> None:
        if self.esc.sync_activation & 0x03 != 0x03:
            self.locked = False
            self.lock_count = 0
        cycle = self.esc.sync0_cycle_ns
        for index in (obj.SYNC_OUTPUT, obj.SYNC_INPUT):
            self.drive.od.set(index, 2, cycle)

    def set_silent(self, silent: bool) -> None:
        """Freeze or thaw the firmware; thawing serves a request left in the write mailbox meanwhile."""
        self.silent = silent
        if not silent:
            request = self.esc.take_mailbox_request()
            if request is not None:
                self.mailbox_received(request)

    # ---- status ---------------------------------------------------------------------------------------
    @property
    def in_dc_activation(self) -> bool:
        return (self.esc.sync_activation & 0x03 == 0x03 and not self.locked
                and self.state in (AlState.SAFEOP, AlState.OP))

    # ---- AL state machine -------------------------------------------------------------------------------
    def _request(self, requested: int) -> None:
        current = self.state
        self.pending_op = False
        if requested == current:
            return
        if requested == AlState.INIT:
            self._enter(AlState.INIT)
        elif requested == AlState.PREOP:
            if current == AlState.INIT and not self._mailbox_config_ok():
                self._fail(AL_INVALID_MAILBOX_CONFIG)
            else:
                self._enter(AlState.PREOP)
        elif requested == AlState.SAFEOP:
            if current == AlState.INIT:
                self._fail(AL_INVALID_STATE_CHANGE)
            elif current == AlState.PREOP:
                code = self._compile_process_data()
                if code:
                    self._fail(code)
                else:
                    self._enter(AlState.SAFEOP)
            else:
                self._enter(AlState.SAFEOP)
        elif requested == AlState.OP:
            if current != AlState.SAFEOP:
                self._fail(AL_INVALID_STATE_CHANGE)
            elif self.esc.sync_activation & 0x03 == 0x03 and self.esc.sync0_cycle_ns < MIN_CYCLE_S * 1e9:
                self._fail(AL_INVALID_SYNC_CYCLE)
            elif self.esc.sync_activation & 0x03 == 0x03 and not self.locked:
                self.pending_op = True
            else:
                self._enter(AlState.OP)
        elif requested == AlState.BOOT:
            self._fail(AL_BOOTSTRAP_NOT_SUPPORTED)
        else:
            self._fail(AL_UNKNOWN_STATE)

    def _fail(self, code: int, fallback: AlState | None = None) -> None:
        self.error = True
        self.code = code
        if fallback is not None and fallback < self.state:
            self._enter(fallback)
        self._publish()

    def _publish(self) -> None:
        self.esc.set_al_status(int(self.state), self.error, self.code)

    def _enter(self, state: AlState) -> None:
        previous = self.state
        self.state = state
        self.pending_op = False
        esc = self.esc
        if previous == AlState.OP and state != AlState.OP and self.drive.csp_enabled:
            self.drive.fault(ERROR_COMMUNICATION)
        esc.set_sm_deactivated(SM_OUTPUTS, state != AlState.OP)
        esc.set_sm_deactivated(SM_INPUTS, state not in (AlState.SAFEOP, AlState.OP))
        if state == AlState.OP:
            esc.last_output_write_ns = esc.frame_time_ns
            self.sync_mismatch = 0
        if state <= AlState.PREOP:
            self.locked = False
            self.lock_count = 0
            self.outputs_pending = False
        if state == AlState.INIT:
            self.coe.reset()
            self._replies.clear()
            esc.clear_mailboxes()
        self._publish()

    def _mailbox_config_ok(self) -> bool:
        size = self.options.mailbox_size
        out_start, out_length, out_control, out_activate = self.esc.sync_manager(0)
        in_start, in_length, in_control, in_activate = self.esc.sync_manager(1)
        expected = sii_content(self.options, 0).sync_managers
        return (out_start == expected[0].start and out_length == size and out_control & 0x0F == 0x06
                and out_activate & 0x01 and in_start == expected[1].start and in_length == size
                and in_control & 0x0F == 0x02 and in_activate & 0x01)

    def _compile_process_data(self) -> int:
        """Build the PDO codecs from 0x1C12/0x1C13 and check SM2/SM3 against them; an AL code or 0."""
        try:
            rx = self._codec(obj.RXPDO_ASSIGN)
            tx = self._codec(obj.TXPDO_ASSIGN)
        except SdoAbort:
            return AL_INVALID_OUTPUT_CONFIG
        for sm, codec, code, write in ((SM_OUTPUTS, rx, AL_INVALID_OUTPUT_CONFIG, True),
                                       (SM_INPUTS, tx, AL_INVALID_INPUT_CONFIG, False)):
            start, length, control, activate = self.esc.sync_manager(sm)
            if codec.size == 0:
                continue
            if (length != codec.size or not activate & 0x01 or control & 0x03 != 0
                    or bool(control & 0x04) != write or start + length > 0x3000):
                return code
        self.rx = rx
        self.tx = tx
        self._outputs_at = self.esc.sync_manager(SM_OUTPUTS)[0]
        self._inputs_at = self.esc.sync_manager(SM_INPUTS)[0]
        return AL_OK

    def _codec(self, assign_index: int) -> PdoCodec:
        od = self.drive.od
        entries: list[Entry | None] = []
        paddings: list[int] = []
        for i in range(1, int(od.value(assign_index, 0)) + 1):
            pdo = int(od.value(assign_index, i))
            for sub in range(1, int(od.value(pdo, 0)) + 1):
                mapping = int(od.value(pdo, sub))
                index, subindex, bits = mapping >> 16, (mapping >> 8) & 0xFF, mapping & 0xFF
                if index == 0:
                    entries.append(None)
                    paddings.append(bits // 8)
                else:
                    entries.append(od.entry(index, subindex))
                    paddings.append(0)
        return PdoCodec(entries, paddings)

    # ---- PDO mapping objects: writable in PRE-OP only, validated when sub 0 is set -------------------------
    def _guard_pdo_objects(self) -> None:
        od = self.drive.od
        for assign, pdo, direction in ((obj.RXPDO_ASSIGN, obj.RXPDO_MAP, "rx"),
                                       (obj.TXPDO_ASSIGN, obj.TXPDO_MAP, "tx")):
            for sub in range(0, 17):
                od.entry(pdo, sub).on_write = self._mapping_write(pdo, sub, direction)
            od.entry(assign, 0).on_write = self._assign_write(assign, 0, pdo)
            od.entry(assign, 1).on_write = self._assign_write(assign, 1, pdo)

    def _check_preop(self) -> None:
        if self.state != AlState.PREOP:
            raise SdoAbort(ABORT_DEVICE_STATE, "PDO mapping can only change in PRE-OP")

    def _mapping_write(self, pdo: int, sub: int, direction: str) -> Callable[[Entry, int | str], None]:
        def hook(entry: Entry, value: int | str) -> None:
            self._check_preop()
            od = self.drive.od
            if sub != 0:
                if int(od.value(pdo, 0)) != 0:
                    raise SdoAbort(ABORT_SUBINDEX_ZERO_FIRST)
                return
            if not 0 <= int(value) <= 16:
                raise SdoAbort(ABORT_PDO_LENGTH)
            total = 0
            for i in range(1, int(value) + 1):
                mapping = int(od.value(pdo, i))
                index, subindex, bits = mapping >> 16, (mapping >> 8) & 0xFF, mapping & 0xFF
                if bits % 8:
                    raise SdoAbort(ABORT_NOT_MAPPABLE, f"0x{index:04X}:{subindex:02X} bit length {bits}")
                if index != 0:
                    target = od.entry(index, subindex) if (index, subindex) in od else None
                    if target is None or target.pdo != direction or target.bits != bits:
                        raise SdoAbort(ABORT_NOT_MAPPABLE, f"0x{index:04X}:{subindex:02X}")
                total += bits // 8
            if total > MAX_PDO_BYTES:
                raise SdoAbort(ABORT_PDO_LENGTH)
        return hook

    def _assign_write(self, assign: int, sub: int, pdo: int) -> Callable[[Entry, int | str], None]:
        def hook(entry: Entry, value: int | str) -> None:
            self._check_preop()
            if sub == 0 and int(value) > 1:
                raise SdoAbort(ABORT_PDO_LENGTH)
            if sub == 1 and int(value) != pdo:
                raise SdoAbort(ABORT_NOT_MAPPABLE, f"only 0x{pdo:04X} can be assigned")
        return hook

    # ---- mailbox ------------------------------------------------------------------------------------------
    def _downloaded(self, index: int, sub: int, data: bytes) -> None:
        if self.log is not None:
            applied = self.drive.last_gain_write_applied if index in (0x2381, 0x2382) else True
            self.log(self.esc.frame_time_ns / 1e9, self.position, index, sub, int.from_bytes(data, "little"), applied)

    def _post_reply(self, now_ns: int) -> None:
        if self._replies and self._replies[0][0] <= now_ns and not self.esc.reply_mailbox_full:
            self.esc.post_mailbox(self._replies.popleft()[1])

    # ---- process data and time ---------------------------------------------------------------------------
    def on_cycle(self, now_ns: int, time_distributed: bool) -> None:
        """A process-data frame reached this slave's FMMUs (``time_distributed``: it also carried the
        master's 0x0910 time distribution)."""
        if self.silent:
            return
        previous = self.last_cycle_ns
        self.last_cycle_ns = now_ns
        if self.state not in (AlState.SAFEOP, AlState.OP) or not self.esc.sync0_running(now_ns):
            return
        limit = self.esc.sync0_cycle_ns * (1.0 + self.options.sync_tolerance)
        too_slow = previous is not None and now_ns - previous > limit
        difference = self.esc.dc_difference_ns if self.esc.dc_sample_ns == now_ns else None  # this frame's sample
        off_time = time_distributed and difference is not None and abs(difference) > self.options.dc_sync_window_ns
        if not self.locked:
            if too_slow or off_time:
                self.lock_count = 0
            elif time_distributed:
                self.lock_count += 1
                if self.lock_count >= self.options.dc_lock_cycles:
                    self.locked = True
                    if self.pending_op:
                        self._enter(AlState.OP)
            return
        if self.state != AlState.OP:
            if off_time:
                self.locked = False
                self.lock_count = 0
            return
        self.sync_mismatch = self.sync_mismatch + 1 if too_slow or off_time else 0
        if self.sync_mismatch >= self.options.sync_fault_cycles:
            self.sync_mismatch = 0
            self.drive.fault(ERROR_COMMUNICATION)
            self.locked = False
            self.lock_count = 0
            self._fail(AL_SYNC_ERROR, AlState.SAFEOP)

    def apply_outputs(self) -> None:
        """Decode outputs the master completed in this frame and let the drive react."""
        self.outputs_pending = False
        if self.silent or self.rx is None or self.state != AlState.OP:
            return
        self.rx.unpack(self.esc.mem, self._outputs_at)
        self.drive.process_outputs()

    def refresh_inputs(self) -> None:
        if self.silent or self.tx is None:
            return
        self.tx.pack(self.esc.mem, self._inputs_at)

    def deliver_replies(self, now_ns: int) -> None:
        """Move a mailbox reply whose latency has passed into the read mailbox."""
        if self._replies and not self.silent:
            self._post_reply(now_ns)

    def tick(self, now_ns: int) -> None:
        """Time-driven checks: delayed mailbox replies, output watchdog, CSP without DC."""
        if self.silent:
            return
        if self._replies:
            self._post_reply(now_ns)
        if self.pending_change is not None and now_ns >= self.pending_change[1]:
            requested, self.pending_change = self.pending_change[0], None
            self._request(requested)
            self._publish()
        if self.state != AlState.OP:
            return
        watchdog = self.esc.output_watchdog_ns
        last = self.esc.last_output_write_ns
        if watchdog and last is not None and now_ns - last > watchdog:
            self._fail(AL_WATCHDOG, AlState.SAFEOP)
            return
        if self.drive.csp_enabled and not self.esc.sync0_running(now_ns):
            self.drive.fault(ERROR_COMMUNICATION)

    def _new_drive(self, serial: int) -> ErobDrive:
        return ErobDrive(serial, gain_bytes=self.options.gain_bytes, rated_torque_mnm=self.options.rated_torque_mnm)

    def power_cycle(self, now_ns: int | None = None) -> None:
        """The slave lost power and came back at ``now_ns``: ESC registers, its local clock, AL state and the drive
        start afresh."""
        self.drive = self._new_drive(self.drive.serial)  # the same model as before, factory state
        self.coe = CoeServer(self.drive.od, self.options.mailbox_size, on_download=self._downloaded)
        self._guard_pdo_objects()
        self.esc.power_on(now_ns)
        self.pending_change = None
        self.state = AlState.INIT
        self.error = False
        self.code = AL_OK
        self.rx = None
        self.tx = None
        self.last_cycle_ns = None
        self._enter(AlState.INIT)
