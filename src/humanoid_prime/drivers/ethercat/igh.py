"""SDO access through the IgH master's ``ethercat`` command-line tool, for machines where IgH owns the NIC.

Only SDO upload/download and the slave list are used (``ethercat upload|download -pN INDEX SUB [VALUE]
--type T``, ``ethercat slaves -v``); the cycle stays with whatever application runs on the IgH master.
Upload prints ``0x<hex> <decimal>`` (e.g. ``0x0000001e 30``). Every failure of the tool becomes one line
naming the command, its exit status and the tool's own first line of explanation.

The SDO rule of DESIGN §3 holds here too: mailbox traffic while slaves are being activated (SAFE-OP, or
a mix of states) faults a drive with 0xA000, so the first transfer, and the first after any failure,
checks that every slave is in OP or that the whole ring idles in PRE-OP.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import threading

from humanoid_prime.drivers.ethercat.errors import RingError, SdoError, SdoRefused
from humanoid_prime.drivers.ethercat.ring import SlaveInfo
from humanoid_prime.drivers.ethercat.slave_config import PDO_TYPES
from humanoid_prime.drivers.ethercat.wire import AL_ERROR, AL_STATE_MASK, AlState

# IgH data type names: (bytes, signed). The short names are what `prime ec sdo --type` accepts.
IGH_TYPES: dict[str, tuple[int, bool]] = {
    "uint8": (1, False), "uint16": (2, False), "uint32": (4, False),
    "int8": (1, True), "int16": (2, True), "int32": (4, True),
}
SHORT_TYPES = {"u8": "uint8", "u16": "uint16", "u32": "uint32", "i8": "int8", "i16": "int16", "i32": "int32"}
_UNSIGNED_BY_SIZE = {1: "uint8", 2: "uint16", 4: "uint32"}
_AL_STATES: dict[str, int] = {"INIT": AlState.INIT, "PREOP": AlState.PRE_OP, "BOOT": AlState.BOOT,  # as `ethercat
                              "SAFEOP": AlState.SAFE_OP, "OP": AlState.OP}  # slaves` names them
_VALUE = re.compile(r"^0x([0-9a-fA-F]+)\s+(-?\d+)\s*$")
_ABORT = re.compile(r"aborted with code 0x([0-9a-fA-F]{8})")


def parse_upload(text: str, type_name: str | None) -> tuple[int, int]:
    """(value, size in bytes) from ``ethercat upload`` output such as ``0x0000001e 30``.

    Without a type (the tool took it from the slave's dictionary) the size is the printed hex width.
    """
    line = text.strip().splitlines()[0] if text.strip() else ""
    match = _VALUE.match(line)
    if match is None:
        raise ValueError(f"unexpected output {line!r} (expected '0x<hex> <decimal>')")
    value = int(match.group(2))
    size = IGH_TYPES[type_name][0] if type_name else max(1, len(match.group(1)) // 2)
    return value, size


def parse_slaves(text: str) -> tuple[SlaveInfo, ...]:
    """Slaves from ``ethercat slaves -v``: position, state, identity and device name."""
    slaves = []
    fields: dict[str, str] = {}

    def flush() -> None:
        if fields:
            state_text = fields.get("State", "")
            state = _AL_STATES.get(state_text.split("+")[0].strip().upper(), 0)
            if "ERR" in state_text.upper() or fields.get("Flag", "+").strip() == "E":
                state |= AL_ERROR
            slaves.append(SlaveInfo(
                position=int(fields["position"]),
                name=fields.get("Device name", "").strip(),
                vendor_id=int(fields.get("Vendor Id", "0"), 16),
                product_code=int(fields.get("Product code", "0"), 16),
                revision=int(fields.get("Revision number", "0"), 16),
                al_state=state,
            ))
            fields.clear()

    for line in text.splitlines():
        header = re.match(r"^=== (?:Master \d+, )?Slave (\d+) ===", line.strip())
        if header:
            flush()
            fields["position"] = header.group(1)
            continue
        key, sep, value = line.strip().partition(":")
        key = key.strip()
        if sep and fields and key not in fields:
            fields[key] = value.strip()
    flush()
    return tuple(slaves)


class IghSdo:
    """SDO client over the IgH ``ethercat`` tool; same ``sdo_read``/``sdo_write`` as the in-process master."""

    def __init__(self, master_index: int = 0, *, executable: str = "ethercat", timeout_s: float = 5.0) -> None:
        self.master_index = master_index
        self.executable = executable
        self.timeout_s = timeout_s
        self._settled = False
        self._lock = threading.Lock()

    # ------------------------------------------------------------------------------- tool
    def _run(self, args: list[str], *, position: int | None = None, index: int = 0, sub_index: int = 0) -> str:
        tool = shutil.which(self.executable)
        if tool is None:
            raise RingError(f"the IgH `{self.executable}` tool is not on PATH: install the IgH EtherCAT master "
                            "or use --backend soem")
        command = [tool, "-m", str(self.master_index), *args]
        shown = " ".join([self.executable, *args])
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=self.timeout_s, check=False)
        except subprocess.TimeoutExpired:
            self._settled = False
            raise RingError(f"`{shown}` did not finish within {self.timeout_s:g} s") from None
        if done.returncode == 0:
            return done.stdout
        self._settled = False
        reason = next((line.strip() for line in (done.stderr + "\n" + done.stdout).splitlines() if line.strip()),
                      "no explanation printed")
        if position is not None:
            abort = _ABORT.search(reason)
            raise SdoError(position, index, sub_index, f"`{shown}` failed (exit {done.returncode}): {reason}",
                           int(abort.group(1), 16) if abort else None)
        raise RingError(f"`{shown}` failed (exit {done.returncode}): {reason}")

    def slaves(self) -> tuple[SlaveInfo, ...]:
        """Every slave the IgH master sees, with identity and AL state."""
        return parse_slaves(self._run(["slaves", "-v"]))

    def _require_settled(self, position: int, index: int, sub_index: int) -> None:
        with self._lock:
            if self._settled:
                return
            states = {s.al_state for s in self.slaves()}
            if states == {AlState.OP} or states == {AlState.PRE_OP}:
                self._settled = True
                return
        names = ", ".join(sorted(_state_name(s) for s in states)) or "no slaves"
        raise SdoRefused(position, index, sub_index,
                         f"refused: the IgH ring is not settled (slaves in {names}); mailbox traffic while slaves "
                         "are activated faults a drive with 0xA000; retry when every slave is in OP")

    # -------------------------------------------------------------------------------- SDO
    def upload(self, position: int, index: int, sub_index: int, type_name: str | None = None) -> tuple[int, int]:
        """(value, size in bytes) of one object entry; ``type_name`` is an IgH type or None for the dictionary's."""
        if type_name is not None and type_name not in IGH_TYPES:
            raise ValueError(f"unknown type {type_name!r}; use one of {', '.join(IGH_TYPES)}")
        self._require_settled(position, index, sub_index)
        args = ["upload", f"-p{position}", f"0x{index:04X}", f"0x{sub_index:02X}"]
        if type_name:
            args += ["--type", type_name]
        out = self._run(args, position=position, index=index, sub_index=sub_index)
        try:
            return parse_upload(out, type_name)
        except ValueError as exc:
            raise SdoError(position, index, sub_index, f"`ethercat {' '.join(args)}`: {exc}") from None

    def download(self, position: int, index: int, sub_index: int, value: int, type_name: str) -> None:
        _, lo, hi = PDO_TYPES[type_name]
        if not lo <= value <= hi:
            raise SdoError(position, index, sub_index, f"value {value} does not fit {type_name} ({lo}..{hi})")
        self._require_settled(position, index, sub_index)
        self._run(["download", f"-p{position}", f"0x{index:04X}", f"0x{sub_index:02X}", str(value),
                   "--type", type_name], position=position, index=index, sub_index=sub_index)

    def sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        value, size = self.upload(position, index, sub_index)
        return value.to_bytes(size, "little", signed=value < 0)

    def sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        type_name = _UNSIGNED_BY_SIZE.get(len(data))
        if type_name is None:
            raise SdoError(position, index, sub_index, f"{len(data)} bytes cannot be written with the IgH tool "
                                                       "(1, 2 or 4 bytes only)")
        self.download(position, index, sub_index, int.from_bytes(data, "little"), type_name)


def _state_name(state: int) -> str:
    names = {v: k for k, v in _AL_STATES.items()}
    text = names.get(state & AL_STATE_MASK, f"0x{state & AL_STATE_MASK:X}")
    return f"{text}+ERROR" if state & AL_ERROR else text
