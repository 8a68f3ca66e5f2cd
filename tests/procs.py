"""Other processes as /proc shows them: whether one has exited, and whose parent is whom (Linux); and a
`tether` command run as one."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest


def _stat(pid: int) -> list[str]:
    """The fields of /proc/PID/stat after the command name: state, ppid, ..."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def gone(pid: int) -> bool:
    """The process has exited (a zombie left for a parent that does not reap it counts as exited)."""
    try:
        return _stat(pid)[0] in ("Z", "X")
    except FileNotFoundError:
        return True


def children(pid: int) -> list[int]:
    """The processes whose parent is `pid` (started by any of its threads), from its own /proc entry:
    quick enough to poll for a fork as it happens, where scanning all of /proc is not."""
    found: list[int] = []
    with contextlib.suppress(OSError):  # `pid` gone: none
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(OSError):  # the thread ended meanwhile
                found += [int(child) for child in (task / "children").read_text().split()]
    return found


@contextlib.contextmanager
def tether_process(env: dict[str, str], *args: str, own_session: bool = True) -> Iterator[subprocess.Popen[str]]:
    """`tether ARGS` in a session of its own (a signal sent to it reaches it alone), its output piped
    as text; killed at the end if it still runs. `own_session` False: in the caller's session, sharing
    its CPU (Linux's autogroup scheduling gives each session a share of its own)."""
    process = subprocess.Popen(
        [sys.executable, "-m", "tether", *args],
        # A crash (a signal's SIGSEGV or SIGABRT) says where on stderr: CI saw a command stopped by a
        # Ctrl-C end with no output at all, twice, never here.
        env={**env, "PYTHONFAULTHANDLER": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=own_session,
    )
    try:
        yield process
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()


def output_of(process: subprocess.Popen[str], timeout: float) -> tuple[str, str]:
    """What a `tether_process` printed (stdout, stderr) once it ended. One still running after
    `timeout` fails the test with its output and, from the fault handler, every thread's stack: it
    is sent SIGABRT (a CI run saw `send --wait` not end after a Ctrl-C, and nothing to go on)."""
    try:
        return process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGABRT)
        try:
            out, err = process.communicate(timeout=10.0)
        except subprocess.TimeoutExpired:
            process.kill()
            out, err = process.communicate()
        pytest.fail(f"still running after {timeout:g} s; stdout {out!r}; stderr (the stacks at the end): {err[-6000:]}")


def wait_until(condition: Callable[[], bool], timeout: float) -> bool:
    """Whether `condition()` came true within `timeout` seconds (polled: another process's state)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True
