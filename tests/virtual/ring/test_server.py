"""The emulator's scheduling: real time where permitted, never lowered below what its process asked for."""

import json
import subprocess
import sys

import pytest

CHILD = """
import json
import os
from humanoid_prime.virtual.ring.server import raise_to_realtime
seen = []
for priority in (20, 70, 20):
    raise_to_realtime(priority)
    seen.append((os.sched_getscheduler(0) == os.SCHED_FIFO, os.sched_getparam(0).sched_priority))
print(json.dumps(seen))
"""


def test_the_ring_servers_priority_does_not_lower_the_virtual_primes():
    result = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    seen = json.loads(result.stdout)
    if not seen[0][0]:
        pytest.skip("real-time scheduling is not permitted here")
    assert seen == [[True, 20], [True, 70], [True, 70]]
