"""Loopback ports for tests' Zenoh sessions to listen on (see tether.supervisor.free_base_port), and the
robot's heartbeat bounds for tests on a loaded machine."""

from __future__ import annotations

import os

from tether.supervisor import free_base_port

# How long the robot goes on without safety's heartbeat, and the oldest heartbeat it takes (the sim's
# [sim] heartbeat_timeout and heartbeat_max_age, 0.2 and 0.5 s by default), where a test is not about
# those bounds: `make test` runs three workers of stacks on two cores (tests/suite.py), and a loaded machine can
# keep a process off the CPU for longer than the defaults. The robot then stops as it should, and a
# test about something else fails for a reason it does not test.
LOADED_HEARTBEAT_TIMEOUT = 1.0
LOADED_HEARTBEAT_MAX_AGE = 1.5


def worker_band() -> tuple[int, int]:
    """This test process's slice of the port range, as (index, of how many).

    A pytest-xdist worker gwN takes band N; tests/suite.py runs a second pytest beside the workers
    and gives it the band after theirs (TETHER_TEST_PORT_BAND, of TETHER_TEST_PORT_BANDS). Alone: all.
    """
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    own = os.environ.get("TETHER_TEST_PORT_BAND")
    if not worker.startswith("gw") and own is None:
        return (0, 1)
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    bands = int(os.environ.get("TETHER_TEST_PORT_BANDS", str(workers)))
    return (int(worker[2:]) if worker.startswith("gw") else int(own or 0), bands)


def free_ports(size: int = 1) -> int:
    """The first of `size` consecutive loopback ports that are free now, in this worker's band."""
    return free_base_port(size, worker_band())


def free_port() -> int:
    """A loopback port free now, for one test's sessions to listen on."""
    return free_ports(1)
