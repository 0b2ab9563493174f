"""A CoE object dictionary: typed entries with access rules, value ranges and write hooks; an access it refuses
raises SdoAbort with the code (``drivers/ethercat/wire.py``) the slave answers with.

Values are Python ints (or str for visible strings); ``encode``/``decode`` convert to and from the
little-endian wire bytes. A write of another length than the entry's own is refused (0x06070010), as a
CoE stack that enforces sizes does.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from humanoid_prime.drivers.ethercat.slave_config import PDO_TYPES
from humanoid_prime.drivers.ethercat.wire import (
    ABORT_LENGTH,
    ABORT_NO_OBJECT,
    ABORT_NO_SUBINDEX,
    ABORT_READ_ONLY,
    ABORT_VALUE_HIGH,
    ABORT_VALUE_LOW,
    ABORT_WRITE_ONLY,
)

READ_ONLY = "ro"
READ_WRITE = "rw"

# Object codes and CANopen data types (CiA 301), as the SDO information service reports them.
OBJECT_VAR = 0x07
OBJECT_ARRAY = 0x08
OBJECT_RECORD = 0x09
DATA_TYPES = {"b": 0x0002, "h": 0x0003, "i": 0x0004, "B": 0x0005, "H": 0x0006, "I": 0x0007, "s": 0x0009,
              "q": 0x0015, "Q": 0x001B}

PDO_RX = "rx"  # mappable into an RxPDO (master -> slave)
PDO_TX = "tx"  # mappable into a TxPDO (slave -> master)

_LIMITS = {fmt: (lo, hi) for fmt, lo, hi in PDO_TYPES.values()}


class SdoAbort(Exception):
    """An SDO access the slave refuses; ``code`` is the abort code it answers with."""

    def __init__(self, code: int, text: str = "") -> None:
        super().__init__(f"SDO abort 0x{code:08X}" + (f": {text}" if text else ""))
        self.code = code


@dataclass(eq=False)
class Entry:
    """One subindex. ``fmt`` is a struct code (b B h H i I q) or "s" for a visible string."""

    index: int
    sub: int
    name: str
    fmt: str
    value: int | str
    access: str = READ_WRITE
    pdo: str | None = None
    minimum: int | None = None
    maximum: int | None = None
    # Called with the decoded value before it is stored; may raise SdoAbort, may return a replacement.
    on_write: Callable[[Entry, int | str], int | str | None] | None = None
    # Called before a read so a live value (position, time) can be refreshed.
    on_read: Callable[[Entry], None] | None = None
    _struct: struct.Struct | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.fmt != "s":
            self._struct = struct.Struct("<" + self.fmt)

    @property
    def size(self) -> int:
        return len(str(self.value).encode("ascii")) if self._struct is None else self._struct.size

    @property
    def bits(self) -> int:
        return self.size * 8

    @property
    def access_bits(self) -> int:
        """The SDO information service's object access word: read (bits 0-2) and write (bits 3-5) in PRE-OP,
        SAFE-OP and OP, RxPDO (bit 6) or TxPDO (bit 7) mappable."""
        bits = {READ_ONLY: 0x0007, READ_WRITE: 0x003F, "wo": 0x0038}[self.access]
        return bits | {PDO_RX: 0x0040, PDO_TX: 0x0080, None: 0}[self.pdo]

    def encode(self) -> bytes:
        if self.on_read is not None:
            self.on_read(self)
        if self._struct is None:
            return str(self.value).encode("ascii")
        return self._struct.pack(self.value)

    def decode(self, data: bytes) -> int | str:
        """The value ``data`` carries, checked against the type and range; raises SdoAbort."""
        if self._struct is None:
            return data.decode("ascii", errors="replace")
        if len(data) != self._struct.size:
            raise SdoAbort(ABORT_LENGTH, f"0x{self.index:04X}:{self.sub:02X} is {self._struct.size} bytes, "
                                         f"got {len(data)}")
        signed = self.fmt.islower()
        value = int.from_bytes(data, "little", signed=signed)
        low, high = _LIMITS[self.fmt]
        if self.minimum is not None:
            low = max(low, self.minimum)
        if self.maximum is not None:
            high = min(high, self.maximum)
        if value > high:
            raise SdoAbort(ABORT_VALUE_HIGH, f"{value} > {high}")
        if value < low:
            raise SdoAbort(ABORT_VALUE_LOW, f"{value} < {low}")
        return value


class ObjectDictionary:
    """Entries by (index, subindex). Reads and writes go through ``upload``/``download`` so access rules
    and hooks apply exactly as for an SDO."""

    def __init__(self, entries: Iterable[Entry] = ()) -> None:
        self._entries: dict[tuple[int, int], Entry] = {}
        self._indices: set[int] = set()
        self._objects: dict[int, tuple[str, int]] = {}  # index -> (name, object code) of non-VAR objects
        for entry in entries:
            self.add(entry)

    def add(self, entry: Entry) -> Entry:
        self._entries[(entry.index, entry.sub)] = entry
        self._indices.add(entry.index)
        return entry

    def name_object(self, index: int, name: str, code: int = OBJECT_RECORD) -> None:
        """Name a multi-entry object (an ARRAY or a RECORD); a VAR object is named by its one entry."""
        self._objects[index] = (name, code)

    @property
    def indices(self) -> list[int]:
        """Every object index, in ascending order (the SDO information service's object list)."""
        return sorted(self._indices)

    def subs(self, index: int) -> list[Entry]:
        return sorted((e for (i, _), e in self._entries.items() if i == index), key=lambda e: e.sub)

    def describe(self, index: int) -> tuple[str, int, int, int]:
        """(name, object code, data type, highest subindex) of an object; SdoAbort 0x06020000 if absent."""
        if index not in self._indices:
            raise SdoAbort(ABORT_NO_OBJECT, f"0x{index:04X}")
        subs = self.subs(index)
        if index not in self._objects:
            only = subs[0]
            return only.name, OBJECT_VAR, DATA_TYPES[only.fmt], only.sub
        name, code = self._objects[index]
        element = subs[-1].fmt if code == OBJECT_ARRAY else None
        return name, code, DATA_TYPES[element] if element else 0x0000, subs[-1].sub

    def __contains__(self, key: tuple[int, int]) -> bool:
        return key in self._entries

    def entry(self, index: int, sub: int) -> Entry:
        """The entry at index:sub; SdoAbort 0x06020000 / 0x06090011 when it does not exist."""
        entry = self._entries.get((index, sub))
        if entry is None:
            if index not in self._indices:
                raise SdoAbort(ABORT_NO_OBJECT, f"0x{index:04X}")
            raise SdoAbort(ABORT_NO_SUBINDEX, f"0x{index:04X}:{sub:02X}")
        return entry

    def upload(self, index: int, sub: int) -> bytes:
        entry = self.entry(index, sub)
        if entry.access == "wo":
            raise SdoAbort(ABORT_WRITE_ONLY)
        return entry.encode()

    def download(self, index: int, sub: int, data: bytes) -> None:
        entry = self.entry(index, sub)
        if entry.access == READ_ONLY:
            raise SdoAbort(ABORT_READ_ONLY, f"0x{index:04X}:{sub:02X} {entry.name}")
        value = entry.decode(data)
        if entry.on_write is not None:
            replaced = entry.on_write(entry, value)
            if replaced is not None:
                value = replaced
        entry.value = value

    def value(self, index: int, sub: int = 0) -> int | str:
        return self.entry(index, sub).value

    def set(self, index: int, sub: int, value: int | str) -> None:
        """Set a value from the device side (no access check, no hook)."""
        self.entry(index, sub).value = value
