"""A service process's own figures for `tether status`: resident memory and its peak, CPU time, uptime.

Each service reads them about itself (services may run on other hosts than the one asking); and which
process holds a port it cannot listen on.
"""

from __future__ import annotations

import os
import resource
import socket
import sys
import time
from pathlib import Path

from schemas.process import ProcessStatus

STARTED = time.monotonic()
PROC_STATUS = Path("/proc/self/status")


def memory(status_file: Path = PROC_STATUS) -> tuple[int, int]:
    """(resident, peak resident) in bytes: VmRSS and VmHWM from /proc; where there is no /proc (not
    Linux), the peak from getrusage for both."""
    try:
        text = status_file.read_text()
    except OSError:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        peak *= 1 if sys.platform == "darwin" else 1024  # bytes on macOS, kB elsewhere
        return peak, peak
    fields = resident_fields(text)
    rss = fields.get("VmRSS", 0)
    return rss, max(rss, fields.get("VmHWM", rss))


def resident_fields(status: str) -> dict[str, int]:
    """VmRSS and VmHWM, in bytes, from the text of a /proc/PID/status (those it holds)."""
    fields: dict[str, int] = {}
    for line in status.splitlines():
        name, _, value = line.partition(":")
        if name in ("VmRSS", "VmHWM"):
            number, *unit = value.split()
            fields[name] = int(number) * (1024 if unit == ["kB"] else 1)
    return fields


def children_memory(proc: Path = Path("/proc")) -> int:
    """What this process's children and their children hold resident, in bytes (0 without /proc)."""
    total = 0
    pending = [os.getpid()]
    while pending:
        try:
            tasks = list((proc / str(pending.pop()) / "task").iterdir())
        except OSError:
            continue  # gone meanwhile, or no /proc
        for task in tasks:
            try:
                children = [int(pid) for pid in (task / "children").read_text().split()]
            except OSError:
                continue
            for child in children:
                try:
                    status = (proc / str(child) / "status").read_text()
                except OSError:
                    continue  # it ended meanwhile
                total += resident_fields(status).get("VmRSS", 0)
                pending.append(child)
    return total


def process_status(service: str) -> ProcessStatus:
    rss, peak = memory()
    times = os.times()
    return ProcessStatus(
        service=service,
        host=socket.gethostname()[:255],
        pid=os.getpid(),
        rss_bytes=rss,
        peak_rss_bytes=peak,
        cpu_seconds=times.user + times.system,
        uptime_seconds=time.monotonic() - STARTED,
        children_rss_bytes=children_memory(),
    )


def port_holders(port: int, proc: Path = Path("/proc")) -> list[tuple[int, str]]:
    """The processes (pid, command line) with a TCP socket bound to local `port`, of those this user may
    look into; none where they cannot be seen (another user's, no /proc)."""
    sockets: set[str] = set()
    for table in ("tcp", "tcp6"):
        try:
            lines = (proc / "net" / table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()  # sl local_address rem_address st ... uid timeout inode
            if len(fields) > 9 and fields[1].rpartition(":")[2] == f"{port:04X}" and fields[9] != "0":
                sockets.add(f"socket:[{fields[9]}]")
    holders: list[tuple[int, str]] = []
    if not sockets:
        return holders
    for process in proc.iterdir():
        if process.name.isdecimal() and sockets & open_files(process):
            try:
                holders.append((int(process.name), command_line(process)))
            except OSError:
                continue  # gone meanwhile
    return holders


def open_files(process: Path) -> set[str]:
    """What a process's descriptors point to (`socket:[INODE]` for a socket); none for another user's."""
    try:
        descriptors = list((process / "fd").iterdir())
    except OSError:
        return set()
    links: set[str] = set()
    for fd in descriptors:
        try:
            links.add(os.readlink(fd))
        except OSError:
            continue  # closed meanwhile (the one that listed them, in this process)
    return links


def command_line(process: Path, limit: int = 200) -> str:
    """A process's command line as one printable line (it is the other process's to choose)."""
    words = (process / "cmdline").read_bytes().rstrip(b"\0").split(b"\0")
    line = " ".join(word.decode(errors="replace") for word in words)
    return "".join(c if c.isprintable() else "?" for c in line)[:limit]
