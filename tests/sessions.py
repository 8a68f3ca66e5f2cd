"""For tests with two real Zenoh sessions in one process: a port nobody listens on."""

from __future__ import annotations

import socket


def free_port() -> int:
    """A loopback port free now, for one test's sessions to listen on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
