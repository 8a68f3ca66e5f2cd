"""Stopping services: a service that ignores SIGTERM leaves its stacks in its log and is killed."""

from __future__ import annotations

import signal
import stat
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from services.robotlink import KEY_ENV
from services.runtime import NodeSettings
from services.safety.operator import TOKEN_ENV
from tether.supervisor import KEY_HOLDERS, LOWEST_PORT, Supervisor, _outgoing_low, free_base_port

# A "service" stuck where SIGTERM cannot reach it: the runtime's handlers, then SIGTERM ignored.
STUCK = """
import signal, time
from services.runtime import stop_event
stop_event()
signal.signal(signal.SIGTERM, signal.SIG_IGN)
print("ready", flush=True)
def stuck_here():
    time.sleep(60)
stuck_here()
"""


def test_a_service_that_does_not_stop_is_killed_after_writing_its_stacks_to_its_log(tmp_path: Path) -> None:
    supervisor = Supervisor(NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}"), tmp_path / "logs", None)
    log = (tmp_path / "logs" / "executor.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-c", STUCK], stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    supervisor.procs["executor"] = proc
    try:
        for _ in range(200):  # up to 10 s for the interpreter to start
            if "ready" in supervisor.log_tail("executor"):
                break
            try:
                proc.wait(timeout=0.05)
            except subprocess.TimeoutExpired:
                continue
        assert "ready" in supervisor.log_tail("executor"), supervisor.log_tail("executor")

        code = supervisor.stop("executor", timeout=0.5)

        assert code == -signal.SIGKILL
        logged = supervisor.log_tail("executor")
        assert "stuck_here" in logged and "Current thread" in logged, logged
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.close()


def settings() -> NodeSettings:
    return NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}")


def test_the_robot_key_is_never_in_the_log_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(KEY_ENV, raising=False)
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    # Without an operator token named: a keys/ directory of its own (0700) beside the logs.
    plain = Supervisor(settings(), tmp_path / "a" / "logs")
    plain.robot_key()
    assert plain.robot_key_file.parent == tmp_path / "a" / "keys"
    assert stat.S_IMODE(plain.robot_key_file.parent.stat().st_mode) == 0o700
    assert stat.S_IMODE(plain.robot_key_file.stat().st_mode) == 0o600
    # With one: beside it, where safety would put the key by itself.
    token = tmp_path / "b" / "secrets" / "operator-token"
    beside = Supervisor(settings(), tmp_path / "b" / "logs", extra_env={TOKEN_ENV: str(token)})
    beside.robot_key()
    assert beside.robot_key_file.parent == token.parent
    for supervisor in (plain, beside):
        assert not list(supervisor.log_dir.iterdir()), "nothing of the key in the log directory"


def test_only_the_key_holders_make_the_key_or_are_told_where_it_is(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # `tether up --deploy DIR --only parser,...` on a host that must not hold the key: none is made.
    monkeypatch.setenv(KEY_ENV, str(tmp_path / "from-the-environment.key"))
    key = tmp_path / "deploy" / "robot1" / "robot.key"
    supervisor = Supervisor(settings(), tmp_path / "logs", extra_env={KEY_ENV: str(tmp_path / "from-extra.key")})
    supervisor.robot_key_file = key
    monkeypatch.setattr(sys, "executable", "/bin/true")  # a real process that exits at once
    try:
        for service in ("parser", "resolver", "executor", "planner", "recorder"):
            supervisor.start(service)
            assert not key.exists(), service
            # Neither the caller's environment nor extra_env tells a non-holder where a key is.
            assert KEY_ENV not in supervisor.env(service), service
        for service in KEY_HOLDERS:
            assert supervisor.env(service)[KEY_ENV] == str(key)
        supervisor.start("safety")
        assert key.exists() and stat.S_IMODE(key.stat().st_mode) == 0o600
    finally:
        supervisor.stop_all()
    assert not (tmp_path / "from-the-environment.key").exists() and not (tmp_path / "from-extra.key").exists()


def test_parallel_workers_choose_ports_from_bands_that_do_not_overlap() -> None:
    top = _outgoing_low()
    first = {free_base_port(9, (0, 2)) for _ in range(50)}
    second = {free_base_port(9, (1, 2)) for _ in range(50)}
    middle = LOWEST_PORT + (top - 9 - LOWEST_PORT) // 2
    assert all(base >= LOWEST_PORT and base + 9 <= middle for base in first)
    assert all(middle <= base and base + 9 <= top for base in second)
    with pytest.raises(ValueError, match="port band 2 of 2"):
        free_base_port(9, (2, 2))


# A service's main thread waiting for its stop, and SIGTERM delivered to another thread (as the
# kernel may: to one of Zenoh's). Python only flags it; the main thread must wake to run the handler.
SIGNALED_ELSEWHERE = """
import signal, threading, time
from services.runtime import stop_event
stop = stop_event()
threading.Thread(target=lambda: (time.sleep(0.2), signal.pthread_kill(threading.get_ident(), signal.SIGTERM))).start()
started = time.monotonic()
stop.wait()
print(f"stopped after {time.monotonic() - started:.2f} s", flush=True)
"""


def test_sigterm_delivered_to_another_thread_still_stops_the_main_thread() -> None:
    done = subprocess.run([sys.executable, "-c", SIGNALED_ELSEWHERE], capture_output=True, text=True, timeout=20)
    assert done.returncode == 0, done.stderr
    assert float(done.stdout.split()[2]) < 2.0, done.stdout
