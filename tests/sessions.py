"""Loopback ports for tests' Zenoh sessions to listen on.

Taken below the range the kernel hands out to outgoing connections: there, one of the sessions'
own outgoing sockets could take a port between the check here and the listen, and a service
would fail to start ("Can not create a new TCP listener").
"""

from __future__ import annotations

import random
import socket
from pathlib import Path

LOWEST = 20000


def _outgoing_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_ports(size: int = 1) -> int:
    """The first of `size` consecutive loopback ports that are free now."""
    highest = max(LOWEST + 1, _outgoing_low() - size)
    for _ in range(200):
        base = random.randrange(LOWEST, highest)
        sockets: list[socket.socket] = []
        try:
            for port in range(base, base + size):
                s = socket.socket()
                sockets.append(s)
                s.bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
        finally:
            for s in sockets:
                s.close()
    raise RuntimeError(f"no {size} free consecutive ports between {LOWEST} and {highest}")


def free_port() -> int:
    """A loopback port free now, for one test's sessions to listen on."""
    return free_ports(1)
