"""The ROS 2 domain of a run: ``--domain`` over ``ROS_DOMAIN_ID`` over 0 (no DDS import: the CLI checks it
before anything starts)."""

from __future__ import annotations

import os

from humanoid_prime.errors import PrimeError

DOMAIN_ENV = "ROS_DOMAIN_ID"
MAX_DOMAIN_ID = 232  # the largest ROS 2 domain id whose ports stay below 65535 (ROS 2 "The ROS_DOMAIN_ID")


def domain_id(given: int | None = None) -> int:
    """``given``, else ``ROS_DOMAIN_ID``, else 0; refused with the reason when outside ROS 2's range."""
    source = "--domain"
    if given is None:
        text = os.environ.get(DOMAIN_ENV, "").strip()
        if not text:
            return 0
        source = DOMAIN_ENV
        try:
            given = int(text)
        except ValueError:
            raise PrimeError(f"{DOMAIN_ENV}={text!r} is not a domain id (an integer 0-{MAX_DOMAIN_ID})") from None
    if not 0 <= given <= MAX_DOMAIN_ID:
        raise PrimeError(f"{source} {given} is outside the ROS 2 domain ids 0-{MAX_DOMAIN_ID}")
    return given
