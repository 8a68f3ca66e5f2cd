"""Loopback ports for tests' Zenoh sessions to listen on (see tether.supervisor.free_base_port)."""

from __future__ import annotations

import os

from tether.supervisor import free_base_port


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
