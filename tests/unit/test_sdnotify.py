"""sd_notify against a real unix datagram socket, as systemd listens on one."""

from __future__ import annotations

import os
import socket
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.sdnotify import MIN_FEED_PERIOD, Notifier, socket_address, watchdog_period


@pytest.fixture
def listener(tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify"
    sock.bind(str(path))
    sock.settimeout(5.0)
    try:
        yield sock, str(path)
    finally:
        sock.close()


def received(sock: socket.socket) -> list[str]:
    return sock.recv(4096).decode().split("\n")


def test_ready_status_stopping_arrive_as_datagrams(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    notifier = Notifier({"NOTIFY_SOCKET": path})
    notifier.ready("serving")
    assert received(sock) == ["READY=1", "STATUS=serving"]
    notifier.status("busy")
    assert received(sock) == ["STATUS=busy"]
    notifier.stopping()
    assert received(sock) == ["STOPPING=1"]


def test_abstract_socket_named_with_at() -> None:
    name = f"tether-test-{uuid.uuid4().hex}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        sock.settimeout(5.0)
        Notifier({"NOTIFY_SOCKET": "@" + name}).ready()
        assert received(sock) == ["READY=1"]


def test_watchdog_fed_at_half_the_timeout(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    now = [100.0]
    notifier = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"}, clock=lambda: now[0])
    assert notifier.period == 1.0
    notifier.ready()
    assert received(sock) == ["READY=1"]
    assert received(sock) == ["WATCHDOG=1"], "ready feeds the watchdog at once"
    sock.settimeout(0.0)
    now[0] += 0.5
    notifier.keepalive()  # a fast loop: not yet half the timeout
    with pytest.raises(BlockingIOError):
        sock.recv(4096)
    now[0] += 0.5
    notifier.keepalive()
    sock.settimeout(5.0)
    assert received(sock) == ["WATCHDOG=1"]


def test_wait_feeds_until_stopped(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    notifier = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "40000"})  # fed every 20 ms
    stop = threading.Event()
    waiter = threading.Thread(target=notifier.wait, args=(stop,))
    waiter.start()
    try:
        assert [received(sock) for _ in range(3)] == [["WATCHDOG=1"]] * 3
    finally:
        stop.set()
        waiter.join(timeout=5.0)
    assert not waiter.is_alive()


@pytest.mark.parametrize(
    ("env", "expected"),
    [
        ({}, None),
        ({"WATCHDOG_USEC": "3000000"}, 1.5),
        ({"WATCHDOG_USEC": "3000000", "WATCHDOG_PID": str(os.getpid())}, 1.5),
        ({"WATCHDOG_USEC": "3000000", "WATCHDOG_PID": "1"}, None),  # systemd watches another process
        ({"WATCHDOG_USEC": "0"}, None),
        ({"WATCHDOG_USEC": "soon"}, None),
        ({"WATCHDOG_USEC": "1"}, MIN_FEED_PERIOD),  # a microsecond: fed every 10 ms, not without pause
    ],
)
def test_watchdog_period_from_environment(env: dict[str, str], expected: float | None) -> None:
    assert watchdog_period(env, os.getpid()) == expected


def test_another_pids_watchdog_is_not_fed(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    notifier = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"})
    notifier.ready()
    notifier.keepalive()
    notifier.status("done")
    assert received(sock) == ["READY=1"]
    assert received(sock) == ["STATUS=done"], "no WATCHDOG=1 in between"


def test_no_socket_is_a_no_op() -> None:
    notifier = Notifier({"WATCHDOG_USEC": "2000000"})
    assert not notifier.enabled and notifier.period is None
    assert not notifier.send("READY=1")
    stop = threading.Event()
    stop.set()
    notifier.wait(stop)  # returns at once, sends nothing


def test_unreachable_socket_does_not_raise(tmp_path: Path) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    assert not notifier.send("READY=1")
    notifier.ready()  # still no exception: the service goes on serving


def test_socket_addresses() -> None:
    assert socket_address("/run/systemd/notify") == "/run/systemd/notify"
    assert socket_address("@abstract") == "\0abstract"
    assert socket_address("vsock:2:1234") is None
