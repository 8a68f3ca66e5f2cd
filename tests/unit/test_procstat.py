"""A service's own memory figures (services/procstat.py), and how `tether status` shows them."""

from __future__ import annotations

import logging
import mmap
import os
import resource
import subprocess
import sys
import time
import uuid
from pathlib import Path

import msgspec
import pytest
import zenoh

from schemas import keys
from schemas.process import ProcessStatus
from services.procstat import memory, process_status
from services.runtime import Node, NodeSettings, decoder, encode
from tests.sessions import free_port
from tether.cli import memory_line

MB = 1024 * 1024
PAGE = 4096
BUFFER = 64 * MB
SLACK = 2 * MB

STATUS = """Name:\tpython
Umask:\t0022
State:\tS (sleeping)
VmPeak:\t 2412340 kB
VmSize:\t 2346804 kB
VmHWM:\t  180224 kB
VmRSS:\t  122880 kB
RssAnon:\t   40960 kB
Threads:\t39
"""


def test_resident_and_peak_come_from_vmrss_and_vmhwm(tmp_path: Path) -> None:
    status = tmp_path / "status"
    status.write_text(STATUS)
    assert memory(status) == (120 * MB, 176 * MB)


def test_without_proc_the_peak_stands_for_both(tmp_path: Path) -> None:
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    rss, peak = memory(tmp_path / "missing")
    assert rss == peak
    assert before <= peak <= resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def test_this_process_reports_itself_and_the_report_crosses_the_wire() -> None:
    # A mapping of its own, not a bytearray: whether malloc hands a freed buffer back to the kernel
    # depends on what the process did before (a CI run's worker kept one resident), munmap does not.
    held = mmap.mmap(-1, BUFFER)
    for offset in range(0, BUFFER, PAGE):
        held[offset] = 1  # every page touched, so resident
    holding, _ = memory()
    held.close()  # unmapped: it leaves the process at once
    status = process_status("parser")
    assert (status.service, status.pid) == ("parser", os.getpid())
    assert 0 < status.rss_bytes <= status.peak_rss_bytes
    # The peak remembers the buffer, the resident figure no longer holds it. The kernel counts pages
    # per CPU and /proc adds them up only roughly, so the figures read apart may differ by a few pages:
    # a slack of SLACK, against a buffer of BUFFER.
    assert status.peak_rss_bytes >= holding - SLACK
    assert status.rss_bytes <= holding - BUFFER // 2
    assert status.cpu_seconds > 0 and status.uptime_seconds > 0
    assert decoder(ProcessStatus).decode(encode(status)) == status


def test_status_shows_the_total_then_each_service_in_mb() -> None:
    processes = {
        name: msgspec.structs.asdict(
            ProcessStatus(
                service=name,
                host="h",
                pid=10 + i,
                rss_bytes=rss * MB,
                peak_rss_bytes=rss * MB,
                cpu_seconds=1.0,
                uptime_seconds=5.0,
            )
        )
        for i, (name, rss) in enumerate((("sim", 114), ("parser", 58)))
    }
    assert memory_line(processes) == "memory: 172 MB resident (sim 114, parser 58)"


def test_status_takes_each_process_from_its_own_key_and_drops_one_claiming_another(
    caplog: pytest.LogCaptureFixture,
) -> None:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    with Node("sim", settings) as sim, Node("parser", settings) as liar, Node("cli", settings) as cli:
        sim.declare_alive()
        # On its own key, but saying it is safety.
        claim = encode(msgspec.structs.replace(process_status("parser"), service="safety"))
        key = keys.process_key(settings.robot, "parser")

        def answer(query: zenoh.Query) -> None:
            try:
                query.reply(key, claim)
            finally:
                query.drop()

        queryable = liar.session.declare_queryable(key, answer)
        try:
            assert not cli.wait_alive(["sim"], 10.0)
            # The liar's queryable may reach this session a moment after the sim's token: ask again
            # (within a deadline) until its answer came and was dropped.
            deadline = time.monotonic() + 10.0
            with caplog.at_level(logging.WARNING, logger="services.runtime"):
                found = cli.process_statuses(timeout=2.0)
                while "dropped a process status" not in caplog.text and time.monotonic() < deadline:
                    found = cli.process_statuses(timeout=2.0)
        finally:
            queryable.undeclare()
    assert set(found) == {"sim"} and found["sim"].pid == os.getpid()
    assert "dropped a process status for 'safety'" in caplog.text


def test_a_service_counts_what_its_children_hold() -> None:
    # A real child holding some 64 MB resident (as the sim's renderer holds its meshes) and waiting.
    code = "import sys; held = b'x' * (64 << 20); print('up', flush=True); sys.stdin.read()"
    alone = process_status("sim").children_rss_bytes
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert child.stdout is not None and child.stdout.readline() == b"up\n"
        assert process_status("sim").children_rss_bytes >= alone + 64 * MB
    finally:
        child.communicate(timeout=10)
    assert process_status("sim").children_rss_bytes <= alone
