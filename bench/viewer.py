"""A Foxglove viewer on a bench's stack: `tether view`, and Foxglove's own WebSocket client subscribed to all of it.

`running_view` starts `tether view` on the stack's robot, ports and config file (a free loopback
port, `--json` to learn it; teleop off) and stops it with SIGINT. `running_viewer` runs the client
of tests/integration/foxglove_client (@foxglove/ws-protocol under node) in its `subscribe-all` mode:
it subscribes to every channel the view advertises and reads everything, and with `garbage_hz`
also sends that many rounds a second of garbage frames and bogus client messages on the same
socket. `client_script` installs the client once (`npm ci`) into a cache folder named by the hash
of its files, the same folder the integration tests use.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

from bench.service import BenchError, Progress, Stack, last_line, wait_until
from services import runtime

CLIENT_SOURCE = Path(__file__).resolve().parent.parent / "tests" / "integration" / "foxglove_client"
CLIENT_FILES = ("package.json", "package-lock.json", "client.js")
INSTALL_TIMEOUT = 300.0
VIEW_START_TIMEOUT = 60.0  # s: the view loads the arm's URDF (pinocchio) before it serves
VIEW_STOP_TIMEOUT = 20.0
CLIENT_STOP_TIMEOUT = 10.0
CLIENT_SECONDS = 86400  # the client's own deadline: the bench stops it long before


class ViewerMissing(Exception):
    """What the viewer needs is not on this machine (node, npm, or the client's files); the message says which."""


def client_script(source: Path = CLIENT_SOURCE) -> Path:
    """The client and its node_modules in a cache folder named by the hash of its files (installed once).

    ViewerMissing without node, npm or the client's files; BenchError when `npm ci` fails."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        raise ViewerMissing("node and npm are needed to run Foxglove's WebSocket client (@foxglove/ws-protocol)")
    missing = [f for f in CLIENT_FILES if not (source / f).is_file()]
    if missing:
        raise ViewerMissing(f"the Foxglove client is missing: no {', '.join(missing)} in {source}")
    digest = hashlib.sha256(b"".join((source / f).read_bytes() for f in CLIENT_FILES)).hexdigest()[:16]
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    home = cache / "tether-tests" / f"foxglove-client-{digest}"
    if not (home / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        home.mkdir(parents=True, exist_ok=True)
        for f in CLIENT_FILES:
            shutil.copy(source / f, home / f)
        try:
            done = subprocess.run(
                [npm, "ci", "--no-audit", "--no-fund"],
                cwd=home,
                timeout=INSTALL_TIMEOUT,
                capture_output=True,
                text=True,
            )
        except subprocess.TimeoutExpired:
            raise BenchError(f"npm ci of the Foxglove client in {home} took over {INSTALL_TIMEOUT:g} s") from None
        if done.returncode != 0:
            raise BenchError(f"npm ci of the Foxglove client in {home} failed: {last_line(done.stderr)}")
    return home / "client.js"


class JsonLines:
    """A child's stdout read on a thread of its own, one JSON object a line, as they arrive."""

    def __init__(self, stream: IO[str]) -> None:
        self.lines: list[dict[str, Any]] = []
        self.ended = False
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, args=(stream,), name="bench-json-lines", daemon=True)
        self._thread.start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            try:
                item = json.loads(line)
            except ValueError:
                item = {"unparsed": line.rstrip("\n")}
            with self._lock:
                self.lines.append(item if isinstance(item, dict) else {"unparsed": item})
        self.ended = True

    def find(self, key: str) -> dict[str, Any] | None:
        """The last line with `key`."""
        with self._lock:
            return next((line for line in reversed(self.lines) if key in line), None)

    def wait(self, key: str, timeout: float, what: str, alive: Callable[[], bool] = lambda: True) -> dict[str, Any]:
        """The last line with `key` once there is one; BenchError naming `what` when the output ends first
        or `timeout` seconds pass."""

        def seen() -> bool:
            if self.find(key) is None and (self.ended or not alive()):
                raise BenchError(f"{what}: the process ended first")
            return self.find(key) is not None

        wait_until(seen, timeout, what, poll=0.02)
        found = self.find(key)
        assert found is not None
        return found

    def join(self, timeout: float) -> None:
        self._thread.join(timeout)


def view_log_tail(path: Path) -> str:
    try:
        return path.read_text(errors="replace")[-3000:]
    except OSError:
        return ""


@contextlib.contextmanager
def running_view(stack: Stack, progress: Progress) -> Iterator[tuple[str, subprocess.Popen[str], Path]]:
    """`tether view` on the stack's settings and config (teleop off), on a free loopback port:
    (its URL, its process, its log file) once it serves; stopped with SIGINT, killed if it lingers."""
    env = stack.supervisor.env()
    # The bench's baselines belong to the services: the view answers none of them.
    for name in (runtime.BENCH_ECHO_ENV, runtime.BENCH_RELAY_ENV):
        env.pop(name, None)
    log_path = stack.supervisor.log_dir / "view.log"
    cmd = [sys.executable, "-m", "tether", "view", "--port", "0", "--json"]
    if stack.config_file is not None:
        cmd += ["--config", str(stack.config_file)]
    progress("starting tether view")
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            cmd,
            env=env,
            stdout=subprocess.PIPE,
            stderr=log,
            stdin=subprocess.DEVNULL,
            text=True,
            start_new_session=True,
        )
    try:
        assert proc.stdout is not None
        try:
            started = JsonLines(proc.stdout).wait(
                "ok", VIEW_START_TIMEOUT, "tether view serving", lambda: proc.poll() is None
            )
            if not started["ok"]:
                raise BenchError(f"tether view did not start: {started.get('error')}")
        except BenchError as exc:
            tail = view_log_tail(log_path)
            progress(f"tether view log:\n{tail}")
            raise BenchError(f"{exc} ({last_line(tail)})") from None
        progress(f"tether view serves {started['url']}")
        yield started["url"], proc, log_path
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(timeout=VIEW_STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=10)
        assert proc.stdout is not None
        proc.stdout.close()


class Viewer:
    """The client in subscribe-all mode: its counts as it reports them, and its final ones once stopped."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        self.proc = proc
        self.output = JsonLines(proc.stdout)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def wait_flowing(self, timeout: float) -> dict[str, Any]:
        """Until the client has subscribed and received messages: its counts then."""

        def flowing() -> bool:
            stats = self.output.find("stats")
            if stats is None and (self.output.ended or not self.alive()):
                raise BenchError(f"the Foxglove client ended: {self.output.lines[-3:]}")
            return stats is not None and stats["stats"]["messages"] > 0

        wait_until(flowing, timeout, "messages at the Foxglove client", poll=0.05)
        stats = self.output.find("stats")
        assert stats is not None
        return dict(stats["stats"])

    def stop(self) -> dict[str, Any]:
        """Close its stdin (it then prints its counts with `done` and exits): the counts and why it ended."""
        if self.alive():
            assert self.proc.stdin is not None
            with contextlib.suppress(OSError):
                self.proc.stdin.close()
        try:
            self.proc.wait(timeout=CLIENT_STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self.output.join(CLIENT_STOP_TIMEOUT)
        done = self.output.find("done")
        if done is None:
            raise BenchError(f"the Foxglove client printed no counts (exit code {self.proc.returncode})")
        return done


@contextlib.contextmanager
def running_viewer(script: Path, url: str, garbage_hz: float, log_path: Path, progress: Progress) -> Iterator[Viewer]:
    """The client subscribed to everything at `url` (with `garbage_hz` rounds of garbage a second), its
    stderr in `log_path`; killed at the end if still running."""
    what = f", {garbage_hz:g} rounds of garbage a second" if garbage_hz > 0 else ""
    progress(f"connecting Foxglove's WebSocket client, subscribed to every channel{what}")
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            ["node", str(script), "subscribe-all", url, str(CLIENT_SECONDS), f"{garbage_hz:g}"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            start_new_session=True,  # not stopped by a Ctrl-C: the bench stops it (and kills it, if need be)
        )
    try:
        yield Viewer(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        for stream in (proc.stdin, proc.stdout):
            if stream is not None:
                with contextlib.suppress(OSError):
                    stream.close()
