"""A service process's own figures for `tether status`: resident memory and its peak, CPU time, uptime.

Each service reads them about itself (services may run on other hosts than the one asking).
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
