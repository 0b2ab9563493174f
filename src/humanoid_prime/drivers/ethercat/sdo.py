"""SDO access for tools, by backend name: ``soem`` (this process owns the NIC) or ``igh`` (an IgH master does).

Both give the same blocking ``sdo_read(position, index, sub_index) -> bytes`` and
``sdo_write(position, index, sub_index, data)``, safe to call from one thread per slave at once.
With ``soem`` the ring is brought up here first (mailbox traffic must wait until every slave is in OP and
process data flows), and the master's keeper runs the cycle, drives disabled, until the session ends.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

from humanoid_prime.config.robot import Robot
from humanoid_prime.drivers.ethercat.errors import RingError
from humanoid_prime.drivers.ethercat.ring import expected_ring
from humanoid_prime.drivers.ethercat.sdo_client import SdoClient
from humanoid_prime.errors import PrimeError

SDO_BACKENDS = ("soem", "igh")


def check_backend(name: str) -> str:
    if name not in SDO_BACKENDS:
        raise PrimeError(f"unknown sdo_backend {name!r}; use one of {', '.join(SDO_BACKENDS)}")
    return name


@contextmanager
def open_sdo(backend: str, robot: Robot, *, interface: str | None = None, update_rate: float = 50.0,
             bringup_rate: float = 1000.0, ready_timeout_s: float = 2.0,
             mailbox: str | None = None) -> Iterator[SdoClient]:
    """An SDO client for ``robot``'s ring on ``backend``; the ring must match the hardware file. ``mailbox``: who
    works the mailboxes on the SOEM backend (default: ``buses.ethercat.mailbox``)."""
    hw = robot.hardware
    if check_backend(backend) == "igh":
        from humanoid_prime.drivers.ethercat.igh import IghSdo

        yield IghSdo(hw.ethercat.master)
        return
    from humanoid_prime.drivers.ethercat.soem_master import SoemMaster

    master = SoemMaster(interface or hw.ethercat.interface, update_rate=update_rate,
                        bringup_rate=bringup_rate, mailbox=mailbox or hw.ethercat.mailbox)
    with master:
        master.start(expected_ring(hw.erob_slaves))
        master.exchange()  # process data flows; from here the master's keeper sends it every period
        deadline = time.monotonic() + ready_timeout_s
        while not master.sdo_ready:
            if time.monotonic() > deadline:
                raise RingError(f"process data does not flow on {master.interface} after bring-up "
                                f"(working counter {master.wkc}, expected {master.expected_wkc})")
            time.sleep(0.005)
        yield master
