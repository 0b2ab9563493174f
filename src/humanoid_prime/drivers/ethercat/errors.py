"""The EtherCAT side's errors, apart from every module that raises them (masters, the IgH adapter, SDO clients)."""

from __future__ import annotations

from humanoid_prime.errors import PrimeError


class RingError(PrimeError):
    """The ring cannot be opened, does not match the hardware file, or does not reach OP."""


class SdoError(PrimeError):
    """An SDO transfer failed; names the slave, the object and the reason."""

    def __init__(self, position: int, index: int, sub_index: int, problem: str,
                 abort_code: int | None = None) -> None:
        self.position = position
        self.index = index
        self.sub_index = sub_index
        self.abort_code = abort_code
        self.problem = problem
        super().__init__(f"SDO 0x{index:04X}:{sub_index:02X} on ring {position}: {problem}")


class SdoRefused(SdoError):
    """An SDO was asked for before every slave is in OP with process data flowing."""
