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


class SdoTimeout(SdoError):
    """No reply in time, with what the wait saw: whether the write mailbox took the request, how often the read
    mailbox was looked at, and the longest this process went without talking to the slave (a loaded host's doing,
    not the slave's, when it is a good part of the wait)."""

    def __init__(self, position: int, index: int, sub_index: int, timeout_s: float, *, delivered: bool, looks: int,
                 longest_gap_s: float) -> None:
        self.delivered = delivered
        self.looks = looks
        self.longest_gap_s = longest_gap_s
        self.host_slow = longest_gap_s > timeout_s / 4
        problem = f"no reply within {timeout_s * 1e3:g} ms (mailbox timeout; "
        problem += (f"the request was delivered, its read mailbox looked at {looks} times" if delivered else
                    "its write mailbox never took the request")
        if self.host_slow:
            problem += f"; this process went {longest_gap_s * 1e3:.0f} ms without a look (a loaded host)"
        super().__init__(position, index, sub_index, problem + ")")

    @property
    def verdict(self) -> str:
        """Who kept the reply away, in a few words."""
        if self.host_slow:
            return "this host did not look in time"
        return "the drive did not answer" if self.delivered else "the drive did not take the request"


class SdoRefused(SdoError):
    """An SDO was asked for before every slave is in OP with process data flowing."""
