"""Process management against what goes wrong around it: a notify socket nobody reads, a status that
quotes a file, a supervisor that vanishes, a port someone else holds, a log that only grows."""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest
import zenoh

from services.procstat import port_holders
from services.runtime import NodeSettings
from services.sdnotify import SEND_TIMEOUT, Notifier
from tests.unit.test_sdnotify import listener as listener  # the fixture, shared
from tests.unit.test_sdnotify import received
from tether import supervisor as supervisor_module
from tether.runservice import SUPERVISOR_FD_ENV, port_taken, stop_with_supervisor
from tether.supervisor import MAX_RESTART_DELAY, RESTART_DELAY, STABLE_AFTER, Restarts, Supervisor


def test_a_notify_socket_nobody_reads_does_not_hold_the_caller(listener: tuple[socket.socket, str]) -> None:
    _, path = listener
    notifier = Notifier({"NOTIFY_SOCKET": path})
    results: list[bool] = []

    def feed_until_refused() -> None:
        # The receiver's queue holds net.unix.max_dgram_qlen datagrams (10 by default), then is full.
        for _ in range(1000):
            results.append(notifier.send("WATCHDOG=1"))
            if not results[-1]:
                return

    sender = threading.Thread(target=feed_until_refused, daemon=True)
    sender.start()
    sender.join(timeout=SEND_TIMEOUT + 10.0)
    # (On failure the fixture's close wakes a sender blocked for good.)
    assert not sender.is_alive(), f"a send blocked on a full queue after {len(results)} datagrams"
    assert results[-1] is False and all(results[:-1])


def test_a_keepalive_never_waits_for_room_at_the_manager(listener: tuple[socket.socket, str]) -> None:
    # Safety's heartbeat loop feeds the watchdog: a manager that reads nothing must not stall it.
    _, path = listener
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sender:
        sender.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            for _ in range(100_000):
                sender.sendto(b"STATUS=filler", path)
        now = [100.0]
        notifier = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"}, clock=lambda: now[0])
        took: list[float] = []

        def beat() -> None:
            for _ in range(3):
                now[0] += 1.0  # a feed is due at every call
                started = time.monotonic()
                notifier.keepalive()
                took.append(time.monotonic() - started)

        beating = threading.Thread(target=beat, daemon=True)
        beating.start()
        beating.join(timeout=3 * SEND_TIMEOUT + 10.0)
        assert not beating.is_alive(), "a keepalive blocked on a full queue"
    assert max(took) < SEND_TIMEOUT / 2, took


def test_a_status_with_a_line_break_stays_one_status_line(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    notifier = Notifier({"NOTIFY_SOCKET": path})
    world = "household\nWATCHDOG=trigger\r\nMAINPID=1"  # a world's name, as a world file may spell it
    notifier.ready(f"simulating {world}")
    assert received(sock) == ["READY=1", "STATUS=simulating household WATCHDOG=trigger MAINPID=1"]
    notifier.status(world)
    assert received(sock) == ["STATUS=household WATCHDOG=trigger MAINPID=1"]
    notifier.stopping(world)
    assert received(sock) == ["STOPPING=1", "STATUS=household WATCHDOG=trigger MAINPID=1"]


# A service's first steps under a supervisor: its stop handlers, then the watch on the supervisor.
WATCHED = """
from services.runtime import stop_event
from tether.runservice import stop_with_supervisor
stop = stop_event()
stop_with_supervisor()
print("watching", flush=True)
print("stopped" if stop.wait(60) else "not stopped", flush=True)
"""


def test_a_service_stops_when_the_process_holding_its_lifeline_is_gone() -> None:
    read_end, write_end = os.pipe()
    env = dict(os.environ, **{SUPERVISOR_FD_ENV: str(read_end)})
    proc = subprocess.Popen(
        [sys.executable, "-c", WATCHED], stdout=subprocess.PIPE, text=True, env=env, pass_fds=(read_end,)
    )
    os.close(read_end)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "watching\n"
        os.close(write_end)  # as the kernel closes it when the supervising process dies
        write_end = -1
        out, _ = proc.communicate(timeout=30)
        assert out == "stopped\n" and proc.returncode == 0
    finally:
        if write_end >= 0:
            os.close(write_end)
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_lifeline_that_is_no_pipe_is_ignored_with_a_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="tether.runservice")
    with (tmp_path / "plain").open("w") as plain:
        for value in ("junk", str(plain.fileno())):
            monkeypatch.setenv(SUPERVISOR_FD_ENV, value)
            stop_with_supervisor()
            assert SUPERVISOR_FD_ENV not in os.environ
            assert f"ignoring {SUPERVISOR_FD_ENV}={value!r}" in caplog.text
    assert not [t for t in threading.enumerate() if t.name == "supervisor-watch"]


def test_a_port_in_use_is_named_with_the_process_that_holds_it() -> None:
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        assert os.getpid() in [pid for pid, _ in port_holders(port)]
        conf = zenoh.Config()
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
        with pytest.raises(zenoh.ZError) as raised:
            zenoh.open(conf)
        said = port_taken("parser", raised.value)
    assert said is not None and said.startswith(f"parser cannot listen on tcp/127.0.0.1:{port}: ")
    assert f"in use by pid {os.getpid()} (" in said, said
    assert port_taken("parser", RuntimeError("something else")) is None


def test_a_log_that_outgrew_its_bound_moves_aside_when_its_service_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(supervisor_module, "LOG_ROTATE_BYTES", 1000, raising=False)
    monkeypatch.setattr(sys, "executable", "/bin/true")  # a real process that exits at once
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "parser.log").write_bytes(b"from the run before\n" * 100)
    supervisor = Supervisor(NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}"), logs)
    try:
        supervisor.start("parser").wait(timeout=10)
        assert (logs / "parser.log.1").read_bytes().startswith(b"from the run before")
        assert (logs / "parser.log").stat().st_size == 0
        # Restarted after each crash (`tether up`), its log open all the while: moved aside again.
        supervisor._logs["parser"].write(b"a traceback\n" * 100)
        supervisor._logs["parser"].flush()
        supervisor.start("parser").wait(timeout=10)
        assert (logs / "parser.log.1").read_bytes().startswith(b"a traceback")
        assert (logs / "parser.log").stat().st_size == 0
        assert sorted(p.name for p in logs.iterdir()) == ["parser.log", "parser.log.1"]
    finally:
        supervisor.stop_all()


def test_a_service_that_keeps_exiting_soon_after_its_start_is_restarted_ever_later() -> None:
    """A second `tether up` on the ports of a first restarted its parser twice a second for as long as it ran."""
    restarts = Restarts()
    now = 0.0
    restarts.started("parser", now)
    delays = []
    for _ in range(8):
        now += 0.3  # it exits 0.3 s after each start
        delay = restarts.delay("parser", now)
        delays.append(delay)
        now += delay
        restarts.started("parser", now)
    assert delays == [RESTART_DELAY * 2**i for i in range(5)] + [MAX_RESTART_DELAY] * 3
    # One that ran a while before it exited is restarted at once, and its delay starts over.
    now += STABLE_AFTER + 1.0
    assert restarts.delay("parser", now) == 0.0
    restarts.started("parser", now)
    assert restarts.delay("parser", now + 0.3) == RESTART_DELAY
    # Never started by this supervisor's watch (it died before up watched): at once.
    assert restarts.delay("safety", now) == 0.0
