"""systemd's service notifications (sd_notify): READY, STATUS, STOPPING and the watchdog's WATCHDOG=1.

The protocol is one datagram of `KEY=value` lines to the unix socket named by $NOTIFY_SOCKET (a path,
or an abstract socket written with a leading '@'). It is small enough to speak here: the PyPI
package `sdnotify` has had no release since 2017, and systemd's own python bindings need libsystemd
to build. Without $NOTIFY_SOCKET (not started by systemd with Type=notify) every call does nothing.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)

# The longest a notification may wait for room in the manager's queue: one nobody reads (a manager that
# hangs, a socket left bound by a finished test) fills after a few datagrams, and a blocking send would
# hold the service's main thread there, deaf to its stop. A loop's keepalive does not wait at all.
SEND_TIMEOUT = 1.0
# The shortest feeding period: a WATCHDOG_USEC of a few microseconds (a typo; systemd's smallest useful
# timeout is far longer) would have the feeding loop send without pause, spinning a core.
MIN_FEED_PERIOD = 0.01


def watchdog_period(env: Mapping[str, str], pid: int) -> float | None:
    """How often (seconds) to send WATCHDOG=1: half of $WATCHDOG_USEC, or None when systemd asks for
    no watchdog from this process ($WATCHDOG_PID names another one)."""
    usec, watchdog_pid = env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
    if not usec:
        return None
    try:
        if watchdog_pid and int(watchdog_pid) != pid:
            return None
        timeout = int(usec) / 1e6
    except ValueError:
        log.warning("ignoring a malformed watchdog setting WATCHDOG_USEC=%r WATCHDOG_PID=%r", usec, watchdog_pid)
        return None
    if not timeout > 0:
        return None
    if timeout / 2 < MIN_FEED_PERIOD:
        log.warning("WATCHDOG_USEC=%s is under %g ms: feeding every %g s", usec, 2e3 * MIN_FEED_PERIOD, MIN_FEED_PERIOD)
    return max(timeout / 2, MIN_FEED_PERIOD)


def socket_address(notify_socket: str) -> str | None:
    """$NOTIFY_SOCKET as an AF_UNIX address; None for what we cannot reach (e.g. systemd's vsock: form)."""
    if notify_socket.startswith("@"):
        return "\0" + notify_socket[1:]
    if notify_socket.startswith("/"):
        return notify_socket
    return None


def status_line(text: str) -> str:
    """`STATUS=text` on one line: a status quotes what files hold (a world's name), and a line break in
    it would start an assignment of its own, such as WATCHDOG=trigger (systemd kills the service)."""
    return "STATUS=" + " ".join(text.splitlines())


class Notifier:
    """Tells the service manager how this service is. Safe to call from any thread."""

    def __init__(self, env: Mapping[str, str] | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        env = os.environ if env is None else env
        self._clock = clock
        self._lock = threading.Lock()
        self._address: str | None = None
        self._failed = False
        notify_socket = env.get("NOTIFY_SOCKET", "")
        if notify_socket:
            self._address = socket_address(notify_socket)
            if self._address is None:
                log.warning("NOTIFY_SOCKET=%r is not a unix socket: the service manager hears nothing", notify_socket)
        self.period = watchdog_period(env, os.getpid()) if self._address is not None else None
        self._next_feed = clock()

    @property
    def enabled(self) -> bool:
        return self._address is not None

    def send(self, *lines: str, timeout: float = SEND_TIMEOUT) -> bool:
        """One datagram of `KEY=value` lines; False if it could not be sent within `timeout` seconds
        (logged once, never raised: a service does not stop serving because its manager is not listening)."""
        if self._address is None:
            return False
        message = "\n".join(lines).encode()
        try:
            # A socket per message, as libsystemd does: nothing to keep open or close, a few a second.
            # Connected, so that waiting for room at the receiver sleeps: an unconnected socket polls
            # writable while the receiver's queue is full, and the timeout would be spent spinning.
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
                sock.settimeout(timeout)
                sock.connect(self._address)
                sock.send(message)
        except OSError as exc:
            if not self._failed:
                self._failed = True
                log.warning("cannot notify the service manager at %r: %s", self._address, exc)
            return False
        return True

    def ready(self, status: str = "") -> None:
        """The service is serving: systemd marks it started (and starts watching it)."""
        self.send("READY=1", *([status_line(status)] if status else []))
        self.feed()

    def status(self, text: str) -> None:
        """One line for `systemctl status`."""
        self.send(status_line(text))

    def stopping(self, status: str = "") -> None:
        self.send("STOPPING=1", *([status_line(status)] if status else []))

    def feed(self, timeout: float = SEND_TIMEOUT) -> None:
        """WATCHDOG=1 now (when systemd watches this process)."""
        if self.period is None:
            return
        with self._lock:
            self._next_feed = self._clock() + self.period
        self.send("WATCHDOG=1", timeout=timeout)

    def keepalive(self) -> None:
        """For a loop: WATCHDOG=1 when about half the watchdog timeout passed since the last one (a
        tenth of slack, so a loop that waits exactly `period` between calls feeds every time). Never
        waits for room at the manager: the loop may be safety's heartbeat, which must go on."""
        if self.period is not None and self._clock() >= self._next_feed - self.period / 10:
            self.feed(timeout=0.0)

    def wait(self, stop: threading.Event) -> None:
        """Block until `stop`, feeding the watchdog meanwhile: for a service whose main thread has no
        other work, so a hung interpreter (or a stopped process) is noticed and restarted."""
        if self.period is None:
            stop.wait()
            return
        while not stop.wait(max(0.0, self._next_feed - self._clock())):
            self.feed()
