"""EtherCAT on the wire, each fact written once: frames and datagrams, the ESC registers, AL states and status codes,
the mailbox, CoE and SDO encodings, the SDO abort codes and the SII words. The master (``drivers/ethercat``) and the
emulated slaves (``virtual/ring``) both take them from here.

Sources: ETG.1000.4 (frames, registers, mailbox), ETG.1000.6 (AL states and codes, CoE), CiA 301 (the SDO protocol
and its abort codes), ETG.2010 (the SII); the Beckhoff ESC datasheet, section II, for register bits.
"""

from __future__ import annotations

import struct
from enum import IntEnum

# ---------------------------------------------------------------------------------------------- frames (ETG.1000.4)
ETHERTYPE = 0x88A4
ETH_HEADER_SIZE = 14
ECAT_HEADER_SIZE = 2  # bits 0-10 length of the datagrams, bits 12-15 type
FRAME_TYPE_COMMANDS = 1
DATAGRAM_HEADER = struct.Struct("<BBHHHH")  # command, index, ADP, ADO (or a logical u32), length, IRQ
DATAGRAM_HEADER_SIZE = DATAGRAM_HEADER.size
WKC_SIZE = 2
LENGTH_MASK = 0x07FF  # datagram length field: bits 0-10 the data's length,
CIRCULATING = 0x4000  # bit 14 the circulating frame,
MORE_FOLLOWS = 0x8000  # bit 15 another datagram follows
FIRST_INDEX_OFFSET = ETH_HEADER_SIZE + ECAT_HEADER_SIZE + 1  # the first datagram's index byte in a frame
BROADCAST_MAC = b"\xff" * 6
MASTER_MAC = b"\x01" * 6  # where SOEM sends from (nicdrv.c priMAC); slaves change only bit 1 of its first byte


class Command(IntEnum):
    """Datagram commands."""

    NOP = 0
    APRD = 1
    APWR = 2
    APRW = 3
    FPRD = 4
    FPWR = 5
    FPRW = 6
    BRD = 7
    BWR = 8
    BRW = 9
    LRD = 10
    LWR = 11
    LRW = 12
    ARMW = 13
    FRMW = 14


# ------------------------------------------------------------------------------------------------ ESC registers
REG_FMMU_SM_COUNT = 0x0004  # u8 FMMUs, u8 SyncManagers the ESC has
REG_ESC_FEATURES = 0x0008  # u16; bit 2: distributed clocks (SOEM's hasdc)
ESC_FEATURE_DC = 0x04
REG_STATION_ADDRESS = 0x0010
REG_ALIAS = 0x0012
REG_DL_STATUS = 0x0110
REG_AL_CONTROL = 0x0120  # bits 0-3 the requested state, bit 4 error acknowledge
REG_AL_STATUS = 0x0130  # bits 0-3 the state, bit 4 error indication; then u16 reserved
REG_AL_STATUS_CODE = 0x0134
REG_PDI_CONTROL = 0x0140
REG_WD_DIVIDER = 0x0400
REG_WD_SM_TIME = 0x0420
REG_WD_STATUS = 0x0440
REG_EEPROM_CONFIG = 0x0500  # bit 0: the EEPROM belongs to the PDI (the slave's firmware)
REG_EEPROM_CONTROL = 0x0502  # u16 control/status, then u32 word address, then data
REG_EEPROM_ADDRESS = 0x0504
REG_EEPROM_DATA = 0x0508
REG_FMMU = 0x0600  # FMMU n at REG_FMMU + FMMU_SIZE * n
FMMU_SIZE = 16
REG_SM = 0x0800  # SyncManager n at REG_SM + SM_SIZE * n
SM_SIZE = 8
REG_DC_RECEIVE_TIME = 0x0900  # u32 receive times of ports 0-3; a write latches them
REG_DC_SYSTEM_TIME = 0x0910  # u64; a write is the reference clock's time, a drift sample
REG_DC_FRAME_TIME = 0x0918  # u64 local time at which the latching frame was received
REG_DC_OFFSET = 0x0920  # u64 system time offset
REG_DC_DELAY = 0x0928  # u32 propagation delay from the reference clock
REG_DC_DIFFERENCE = 0x092C  # u32 system time difference: magnitude in bits 0-30, bit 31 see DC_LOCAL_SMALLER
REG_DC_SPEED_START = 0x0930  # u16; a write resets the difference's filter (ESC datasheet section I 9.1.3.6)
REG_DC_CYCLE_UNIT = 0x0980
REG_DC_ACTIVATION = 0x0981  # bit 0 cyclic operation, bit 1 SYNC0, bit 2 SYNC1
REG_DC_SYNC0_START = 0x0990  # u64 system time of the first SYNC0
REG_DC_SYNC0_CYCLE = 0x09A0  # u32 ns

DC_LOCAL_SMALLER = 0x80000000  # 0x092C bit 31: the local copy of the time is the smaller (Infineon XMC4300 manual)
DC_DIFFERENCE_MASK = 0x7FFFFFFF
DC_CYCLIC_SYNC0 = 0x03  # 0x0981: cyclic operation and SYNC0

EEPROM_TO_PDI = 0x01
EEPROM_COMMAND_SHIFT = 8  # 0x0502 bits 8-10: the command
EEPROM_COMMAND_READ = 0x01
EEPROM_COMMAND_WRITE = 0x02
EEPROM_WRITE_ENABLE = 0x0001
EEPROM_READ_8_BYTES = 0x0040  # a read delivers 8 bytes (4 where clear)
EEPROM_NACK = 0x2000
EEPROM_ERRORS = 0x7800
EEPROM_BUSY = 0x8000

SM_LAYOUT = struct.Struct("<HHBBBB")  # start, length, control, status, activate, PDI control
SM_MODE_MASK = 0x03  # control bits 0-1: 00 buffered, 10 mailbox
SM_MODE_MAILBOX = 0x02
SM_DIRECTION_WRITE = 0x04  # control bits 2-3: 01 the master writes
SM_WATCHDOG_TRIGGER = 0x40
SM_STATUS_MAILBOX_FULL = 0x08
SM_ENABLE = 0x01  # activate bit 0
SM_REPEAT = 0x02  # activate bit 1: the mailbox repeat request (PDI control bit 1 acknowledges it)
SM_PDI_DEACTIVATED = 0x01  # PDI control bit 0: the slave switched the SyncManager off
FMMU_LAYOUT = struct.Struct("<IHBBHBBB")  # logical start, length, start bit, end bit, physical start, bit, type, active
FMMU_READ, FMMU_WRITE = 0x01, 0x02


# ---------------------------------------------------------------------------------------- AL states (ETG.1000.6)
class AlState(IntEnum):
    INIT = 0x01
    PRE_OP = 0x02
    BOOT = 0x03
    SAFE_OP = 0x04
    OP = 0x08


AL_STATE_MASK = 0x0F
AL_ERROR = 0x10  # AL status: the error indication; AL control: its acknowledge
AL_STATE_NAMES: dict[int, str] = {AlState.INIT: "INIT", AlState.PRE_OP: "PRE-OP", AlState.BOOT: "BOOT",
                                  AlState.SAFE_OP: "SAFE-OP", AlState.OP: "OP"}

# AL status codes (0x0134); ETG.1000.6 Table 11, named as the specification and SOEM name them. The master ignores
# the code while the error indication is clear (ETG.1000.6 §6.4.1.1): a slave may leave an old one set.
AL_CODE_NO_ERROR = 0x0000
AL_CODE_INVALID_STATE_CHANGE = 0x0011
AL_CODE_UNKNOWN_STATE = 0x0012
AL_CODE_BOOTSTRAP_NOT_SUPPORTED = 0x0013
AL_CODE_INVALID_MAILBOX_CONFIG = 0x0016
AL_CODE_SYNC_ERROR = 0x001A
AL_CODE_WATCHDOG = 0x001B
AL_CODE_INVALID_OUTPUT_CONFIG = 0x001D
AL_CODE_INVALID_INPUT_CONFIG = 0x001E
AL_CODE_NO_SYNC = 0x002D
AL_CODE_INVALID_SYNC_CYCLE = 0x0035
AL_STATUS_CODES: dict[int, str] = {
    AL_CODE_NO_ERROR: "no error",
    0x0001: "unspecified error",
    0x0002: "no memory",
    AL_CODE_INVALID_STATE_CHANGE: "invalid requested state change",
    AL_CODE_UNKNOWN_STATE: "unknown requested state",
    AL_CODE_BOOTSTRAP_NOT_SUPPORTED: "bootstrap not supported",
    0x0014: "no valid firmware",
    0x0015: "invalid mailbox configuration (bootstrap)",
    AL_CODE_INVALID_MAILBOX_CONFIG: "invalid mailbox configuration",
    0x0017: "invalid sync manager configuration",
    0x0018: "no valid inputs available",
    0x0019: "no valid outputs",
    AL_CODE_SYNC_ERROR: "synchronization error",
    AL_CODE_WATCHDOG: "sync manager watchdog",
    0x001C: "invalid sync manager types",
    AL_CODE_INVALID_OUTPUT_CONFIG: "invalid output configuration",
    AL_CODE_INVALID_INPUT_CONFIG: "invalid input configuration",
    0x001F: "invalid watchdog configuration",
    0x0020: "slave needs cold start",
    0x0021: "slave needs INIT",
    0x0022: "slave needs PRE-OP",
    0x0023: "slave needs SAFE-OP",
    0x0024: "invalid input mapping",
    0x0025: "invalid output mapping",
    0x0026: "inconsistent settings",
    0x0027: "free run not supported",
    0x0028: "synchronization not supported",
    0x0029: "free run needs 3-buffer mode",
    0x002A: "background watchdog",
    0x002B: "no valid inputs and outputs",
    0x002C: "fatal sync error",
    AL_CODE_NO_SYNC: "no sync error",
    0x002E: "invalid input FMMU configuration",
    0x0030: "invalid DC SYNC configuration",
    0x0031: "invalid DC latch configuration",
    0x0032: "PLL error",
    0x0033: "DC sync IO error",
    0x0034: "DC sync timeout error",
    AL_CODE_INVALID_SYNC_CYCLE: "DC invalid sync cycle time",
    0x0036: "DC invalid SYNC0 cycle time",
    0x0037: "DC invalid SYNC1 cycle time",
    0x0041: "mailbox AoE error",
    0x0042: "mailbox EoE error",
    0x0043: "mailbox CoE error",
    0x0044: "mailbox FoE error",
    0x0045: "mailbox SoE error",
    0x004F: "mailbox VoE error",
    0x0050: "EEPROM no access",
    0x0051: "EEPROM error",
    0x0060: "slave restarted locally",
    0x0061: "device identification value updated",
    0x00F0: "application controller available",
}


def describe_al_status_code(code: int) -> str:
    """Meaning of an AL status code (0x0134); unknown codes are named as such."""
    return AL_STATUS_CODES.get(code, f"unknown AL status code 0x{code:04X}")


def describe_al_state(state: int) -> str:
    """Name of an AL status register value, e.g. 0x14 -> 'SAFE-OP + ERROR'."""
    name = AL_STATE_NAMES.get(state & AL_STATE_MASK, f"unknown state 0x{state & AL_STATE_MASK:X}")
    return f"{name} + ERROR" if state & AL_ERROR else name


# ------------------------------------------------------------------------------------------- mailbox (ETG.1000.4)
MAILBOX_HEADER = struct.Struct("<HHBB")  # length of what follows, address, channel/priority, type | counter << 4
MAILBOX_HEADER_SIZE = MAILBOX_HEADER.size
MAILBOX_TYPE_MASK = 0x0F
MAILBOX_COUNTER_SHIFT = 4  # counter in bits 4-6: 0 is none (never a repeat), then 1..7, 1 after 7
MAILBOX_COUNTER_MASK = 0x07
MAILBOX_TYPE_ERROR = 0x00
MAILBOX_TYPE_EOE = 0x02
MAILBOX_TYPE_COE = 0x03
MAILBOX_TYPE_NAMES = {0x00: "mailbox error", 0x01: "AoE", 0x02: "EoE", 0x03: "CoE", 0x04: "FoE", 0x05: "SoE",
                      0x0F: "VoE"}
MAILBOX_PROTOCOL_COE = 0x0004  # SII word 0x1C: the mailbox protocols the slave speaks
MAILBOX_ERROR_UNSUPPORTED_PROTOCOL = 0x0002
MAILBOX_ERROR_SERVICE_NOT_SUPPORTED = 0x0004
MAILBOX_ERROR_INVALID_SIZE = 0x0008
MAILBOX_ERRORS = {0x0001: "syntax", MAILBOX_ERROR_UNSUPPORTED_PROTOCOL: "unsupported protocol",
                  0x0003: "invalid channel", MAILBOX_ERROR_SERVICE_NOT_SUPPORTED: "service not supported",
                  0x0005: "invalid header", 0x0006: "size too short", 0x0007: "no more memory",
                  MAILBOX_ERROR_INVALID_SIZE: "invalid size"}


def mailbox_message(payload: bytes, mailbox_type: int, counter: int) -> bytes:
    """A mailbox message: the header, then ``payload``."""
    type_byte = (mailbox_type & MAILBOX_TYPE_MASK) | ((counter & MAILBOX_COUNTER_MASK) << MAILBOX_COUNTER_SHIFT)
    return MAILBOX_HEADER.pack(len(payload), 0, 0, type_byte) + payload


# ----------------------------------------------------------------------------------------------- CoE (ETG.1000.6)
# The CoE header is a u16 after the mailbox header: bits 0-8 a number, bits 12-15 the service.
COE_SERVICE_SHIFT = 12
COE_EMERGENCY = 1
COE_SDO_REQUEST = 2
COE_SDO_RESPONSE = 3
COE_SDO_INFO = 8


def coe_service(coe: bytes) -> int:
    """The service of a CoE payload (its header's top four bits); 0 for a payload too short to say."""
    return coe[1] >> 4 if len(coe) >= 2 else 0


# SDO (CiA 301 §7.2.4.3, as ETG.1000.6 carries it): CoE header u16, command u8, index u16, sub-index u8, 4 data bytes.
SDO_HEADER = struct.Struct("<HBHB")
SDO_MIN_LENGTH = 10
SDO_SPECIFIER_SHIFT = 5  # the command specifier is the command byte's top three bits; the rest is per specifier
# client command specifiers (requests)
CCS_DOWNLOAD_SEGMENT = 0
CCS_DOWNLOAD = 1
CCS_UPLOAD = 2
CCS_UPLOAD_SEGMENT = 3
CS_ABORT = 4  # either direction
# server command specifiers (replies)
SCS_UPLOAD_SEGMENT = 0
SCS_DOWNLOAD_SEGMENT = 1
SCS_UPLOAD = 2
SCS_DOWNLOAD = 3
SCS_NAMES = {SCS_UPLOAD_SEGMENT: "an upload segment", SCS_DOWNLOAD_SEGMENT: "a download segment reply",
             SCS_UPLOAD: "an upload reply", SCS_DOWNLOAD: "a download reply", CS_ABORT: "an abort"}
# bits below the specifier; what a specifier does not define is reserved (ignored on receipt)
SDO_SIZE_INDICATED = 0x01  # initiate: s
SDO_EXPEDITED = 0x02  # initiate: e
SDO_UNUSED_SHIFT = 2  # initiate, expedited and sized: bits 2-3 count the unused of the 4 data bytes
SDO_COMPLETE_ACCESS = 0x10  # initiate request
SDO_TOGGLE = 0x10  # segments
SDO_LAST_SEGMENT = 0x01  # segments: c
SDO_SEGMENT_UNUSED_SHIFT = 1  # a segment of the minimum length: bits 1-3 count its unused data bytes
SDO_SEGMENT_DATA = 7  # data bytes in a segment of the minimum length
# the command bytes Prime sends and the emulated slaves answer with
SDO_DOWNLOAD_NORMAL = CCS_DOWNLOAD << SDO_SPECIFIER_SHIFT | SDO_SIZE_INDICATED  # 0x21, then the size u32
SDO_DOWNLOAD_EXPEDITED = CCS_DOWNLOAD << SDO_SPECIFIER_SHIFT | SDO_EXPEDITED | SDO_SIZE_INDICATED  # 0x23 | n << 2
SDO_UPLOAD_REQUEST = CCS_UPLOAD << SDO_SPECIFIER_SHIFT  # 0x40
SDO_UPLOAD_SEGMENT_REQUEST = CCS_UPLOAD_SEGMENT << SDO_SPECIFIER_SHIFT  # 0x60 | toggle
SDO_ABORT = CS_ABORT << SDO_SPECIFIER_SHIFT  # 0x80, then the abort code u32
SDO_DOWNLOAD_RESPONSE = SCS_DOWNLOAD << SDO_SPECIFIER_SHIFT  # 0x60
SDO_DOWNLOAD_SEGMENT_RESPONSE = SCS_DOWNLOAD_SEGMENT << SDO_SPECIFIER_SHIFT  # 0x20 | toggle
SDO_UPLOAD_RESPONSE = SCS_UPLOAD << SDO_SPECIFIER_SHIFT  # 0x40, with e, s and n as the transfer has them


def command_specifier(command: int) -> int:
    return command >> SDO_SPECIFIER_SHIFT


def sdo_download_expedited(size: int) -> int:
    """The command byte of an expedited download of ``size`` (1 to 4) bytes."""
    return SDO_DOWNLOAD_EXPEDITED | (4 - size) << SDO_UNUSED_SHIFT


def sdo_upload_expedited(size: int) -> int:
    """The command byte of an expedited upload reply of ``size`` (1 to 4) bytes, size indicated."""
    return SDO_UPLOAD_RESPONSE | SDO_EXPEDITED | SDO_SIZE_INDICATED | (4 - size) << SDO_UNUSED_SHIFT


def expedited_size(command: int) -> int:
    """The data bytes an expedited initiate carries: 4 minus the unused count where the size is indicated, else
    all 4 (CiA 301: "d contains unspecified number of bytes"; SOEM, IgH and CANopenNode read 4)."""
    return 4 - ((command >> SDO_UNUSED_SHIFT) & 0x03) if command & SDO_SIZE_INDICATED else 4


# SDO information (ETG.1000.6 §5.6.3): CoE header, opcode (bit 7: more fragments follow), reserved, fragments left
SDO_INFO_HEADER = struct.Struct("<HBBH")
SDO_INFO_INCOMPLETE = 0x80
INFO_OD_LIST_REQUEST, INFO_OD_LIST_RESPONSE = 0x01, 0x02
INFO_OBJECT_REQUEST, INFO_OBJECT_RESPONSE = 0x03, 0x04
INFO_ENTRY_REQUEST, INFO_ENTRY_RESPONSE = 0x05, 0x06
INFO_ERROR = 0x07
INFO_LIST_ALL, INFO_LIST_RX_PDO, INFO_LIST_TX_PDO = 0x01, 0x02, 0x03

# SDO abort codes (CiA 301 §7.2.4.3.17 / ETG.1000.6 Table 41), worded as SOEM's ec_sdoerrorlist words them
ABORT_TOGGLE = 0x05030000
ABORT_TIMEOUT = 0x05040000
ABORT_COMMAND = 0x05040001
ABORT_OUT_OF_MEMORY = 0x05040005
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_SUBINDEX_ZERO_FIRST = 0x06010003
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_LENGTH = 0x06070010
ABORT_LENGTH_HIGH = 0x06070012
ABORT_LENGTH_LOW = 0x06070013
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_VALUE_HIGH = 0x06090031
ABORT_VALUE_LOW = 0x06090032
ABORT_GENERAL = 0x08000000
ABORT_NOT_STORED = 0x08000020
ABORT_DEVICE_STATE = 0x08000022
ABORT_TEXTS = {
    ABORT_TOGGLE: "toggle bit not changed", ABORT_TIMEOUT: "SDO protocol timeout",
    ABORT_COMMAND: "client/server command specifier not valid or unknown", ABORT_OUT_OF_MEMORY: "out of memory",
    ABORT_UNSUPPORTED_ACCESS: "unsupported access to an object",
    ABORT_WRITE_ONLY: "attempt to read a write only object", ABORT_READ_ONLY: "attempt to write a read only object",
    ABORT_SUBINDEX_ZERO_FIRST: "subindex cannot be written, SI0 must be 0 for write access",
    ABORT_NO_OBJECT: "the object does not exist", ABORT_NOT_MAPPABLE: "the object can not be mapped into the PDO",
    ABORT_PDO_LENGTH: "the number and length of the objects to be mapped would exceed the PDO length",
    ABORT_LENGTH: "data type does not match, length of service parameter does not match",
    ABORT_LENGTH_HIGH: "data type does not match, length of service parameter too high",
    ABORT_LENGTH_LOW: "data type does not match, length of service parameter too low",
    ABORT_NO_SUBINDEX: "subindex does not exist", ABORT_VALUE_RANGE: "value range of parameter exceeded",
    ABORT_VALUE_HIGH: "value of parameter written too high", ABORT_VALUE_LOW: "value of parameter written too low",
    ABORT_GENERAL: "general error", ABORT_NOT_STORED: "data cannot be transferred or stored to the application",
    ABORT_DEVICE_STATE: "data cannot be transferred or stored because of the present device state",
}
LENGTH_ABORTS = (ABORT_LENGTH, ABORT_LENGTH_HIGH, ABORT_LENGTH_LOW)  # a write whose size is not the object's


def abort_text(code: int) -> str:
    return ABORT_TEXTS.get(code, "unknown abort code")


# ----------------------------------------------------------------------------------------------- SII (ETG.2010)
SII_WORD_ALIAS = 0x04
SII_WORD_VENDOR = 0x08  # u32 each: vendor, product code, revision, serial number
SII_WORD_PRODUCT = 0x0A
SII_WORD_REVISION = 0x0C
SII_WORD_SERIAL = 0x0E
SII_WORD_MAILBOX = 0x18  # receive mailbox offset and size, send mailbox offset and size, protocols
SII_WORD_SIZE = 0x3E
SII_WORD_CATEGORIES = 0x40
SII_IDENTITY = (SII_WORD_VENDOR, SII_WORD_PRODUCT, SII_WORD_REVISION)
# the General category's CoE details byte, which SOEM reads as CoEdetails
COE_DETAIL_SDO = 0x01
COE_DETAIL_SDO_INFO = 0x02
COE_DETAIL_PDO_ASSIGN = 0x04
COE_DETAIL_PDO_CONFIG = 0x08
COE_DETAIL_UPLOAD_AT_STARTUP = 0x10
COE_DETAIL_COMPLETE_ACCESS = 0x20
