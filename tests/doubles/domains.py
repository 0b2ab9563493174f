"""ROS 2 domain ids for the suite's processes, so that no two tests that may run at once share one.

A run of the suite on parallel workers (pytest-xdist) gives each worker every ``count``-th id of 1..200 from its
own residue; within a worker the ids go round from a start that depends on the process, since other runs of the
suite on this machine may be on the graph at the same time."""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator

IDS = 200  # 1..200: below the 232 a ROS 2 domain id may be, with the ports of every id valid


def domain_ids() -> Iterator[int]:
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw"))
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    span = IDS // count * count  # a whole number of rounds, so every id keeps its worker's residue
    for k in itertools.count(os.getpid() % (IDS // count)):
        yield (k * count + worker) % span + 1
