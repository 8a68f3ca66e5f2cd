"""Loopback ports for tests' Zenoh sessions to listen on (see tether.supervisor.free_base_port)."""

from __future__ import annotations

from tether.supervisor import free_base_port


def free_ports(size: int = 1) -> int:
    """The first of `size` consecutive loopback ports that are free now."""
    return free_base_port(size)


def free_port() -> int:
    """A loopback port free now, for one test's sessions to listen on."""
    return free_base_port(1)
