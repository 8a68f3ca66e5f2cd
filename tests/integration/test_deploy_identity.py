"""`tether deploy init` as a real process: under a permissive umask its files are its owner's alone and
its router still lets each identity in; what it cannot use is one `error:` line, never a traceback."""

from __future__ import annotations

import contextlib
import os
import queue
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from services.runtime import zenoh_config_file
from tests.integration.test_deploy_acl import background
from tests.sessions import free_port

DEADLINE = 30.0


def clean_env() -> dict[str, str]:
    drop = ("TETHER_ROBOT", "TETHER_ZENOH_CONFIG", "TETHER_BASE_PORT", "TETHER_OPERATOR_TOKEN_FILE")
    return {k: v for k, v in os.environ.items() if k not in drop}


def deploy(*args: str, umask: int = 0o022) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "tether", "deploy", "init", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env=clean_env(),
        umask=umask,
    )


def open_when_up(config: Path, proc: subprocess.Popen[bytes]) -> zenoh.Session:
    """A session of that identity, once the router takes it (a person's config does not wait for one)."""
    deadline = time.monotonic() + DEADLINE
    while True:
        assert proc.poll() is None, "the router exited"
        try:
            return zenoh.open(zenoh_config_file(config))
        except zenoh.ZError:
            assert time.monotonic() < deadline, f"{config.name} never got in"
            time.sleep(0.1)  # the next try: the router is still starting


@pytest.mark.parametrize("umask", [0o000, 0o002])
def test_a_deployment_made_under_a_permissive_umask_is_private_and_runs(tmp_path: Path, umask: int) -> None:
    zenoh.init_log_from_env_or("off")
    directory, port = tmp_path / "fleet", free_port()
    made = deploy(str(directory), "--robot", "r1", "--tls", "--router", f"127.0.0.1:{port}", umask=umask)
    assert made.returncode == 0, made.stderr
    for path in [directory, *directory.rglob("*")]:
        found = stat.S_IMODE(path.lstat().st_mode)
        if path.is_dir():
            assert found == 0o700, path  # was 777 (umask 0) or 775: anyone could swap a key or a unit
        else:
            assert not found & 0o022, path

    # The router reads its files and each identity logs in with its own: the agent's e-stop reaches the operator.
    with background(["router", str(directory)], tmp_path / "router.log") as proc:
        received: queue.Queue[bytes] = queue.Queue()
        with (
            open_when_up(directory / "r1" / "operator.json5", proc) as operator,
            open_when_up(directory / "r1" / "agent.json5", proc) as agent,
            operator.declare_subscriber("tether/r1/safety/estop", lambda s: received.put(s.payload.to_bytes())),
        ):
            nonce = os.urandom(8)
            deadline = time.monotonic() + DEADLINE
            got: list[bytes] = []
            while nonce not in got:
                assert time.monotonic() < deadline, "the agent's e-stop never reached the operator"
                agent.put("tether/r1/safety/estop", nonce)
                with contextlib.suppress(queue.Empty):
                    got.append(received.get(timeout=0.2))


def test_what_it_cannot_use_is_one_error_line(tmp_path: Path) -> None:
    """A damaged CA key, a tether.toml that is not TOML, a name systemd cannot take, a shared directory:
    exit 2 and what to do (they were tracebacks, or were accepted)."""
    directory = tmp_path / "fleet"
    assert deploy(str(directory), "--robot", "r1", "--tls").returncode == 0
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)

    ca_key = directory / "ca" / "ca.key"
    kept = ca_key.read_bytes()
    ca_key.write_text("not a key\n")
    damaged = deploy(str(directory), "--robot", "r1", "--tls")
    ca_key.write_bytes(kept)
    (directory / "r1" / "tether.toml").write_text("[safety\n")
    not_toml = deploy(str(directory), "--robot", "r1", "--tls")
    cases = {
        "the CA in": damaged,
        "tether.toml is not valid TOML": not_toml,
        "must be ASCII letters": deploy(str(tmp_path / "other"), "--robot", "robøt"),
        "others may write in": deploy(str(shared), "--robot", "r1"),
    }
    for says, result in cases.items():
        assert result.returncode == 2, (says, result.stderr)
        assert result.stderr.startswith("error:") and says in result.stderr, result.stderr
        assert "Traceback" not in result.stderr
    assert not any(shared.iterdir()) and not (tmp_path / "other").exists()
