"""Which TCP ports of this host are listening now, from the kernel's socket tables (Linux's /proc/net/tcp).

A process joining the loopback stack uses it to know which of the services' ports it can link to at once,
and so how long to wait before it may talk to them (services/runtime.py, Node).
"""

from __future__ import annotations

from pathlib import Path

TCP_TABLES = (Path("/proc/net/tcp"), Path("/proc/net/tcp6"))
LISTEN = "0A"  # the kernel's TCP_LISTEN state, as the tables print it


def listening_in(table: str) -> set[int]:
    """The local ports in state LISTEN in the text of one /proc/net/tcp or tcp6 table."""
    ports: set[int] = set()
    for line in table.splitlines()[1:]:
        fields = line.split()
        if len(fields) < 4 or fields[3] != LISTEN:
            continue
        _, _, port = fields[1].rpartition(":")
        try:
            ports.add(int(port, 16))
        except ValueError:
            continue
    return ports


def listening_ports(tables: tuple[Path, ...] = TCP_TABLES) -> set[int] | None:
    """Every port some socket of this host listens on; None where the tables cannot be read (not Linux)."""
    ports: set[int] = set()
    read = False
    for table in tables:
        try:
            ports |= listening_in(table.read_text())
            read = True
        except OSError:
            continue
    return ports if read else None
