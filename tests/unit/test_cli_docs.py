"""The CLI's outcomes as the README states them: no Zenoh session is exit 3 with one clear line (with
--json one object), never a traceback; `tether up --deploy` waits for its router at most --timeout and
then stops what it started; `send`'s bad usage is exit 2 with one JSON object."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from tests.sessions import free_ports
from tether import cli, deployment

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def router_down(tmp_path: Path) -> Path:
    """A Zenoh client config, as a deployment's operator has, whose router is not running."""
    path = tmp_path / "operator.json5"
    endpoint = f"tcp/127.0.0.1:{free_ports(1)}"
    conf = {"mode": "client", "connect": {"endpoints": [endpoint]}, "scouting": {"multicast": {"enabled": False}}}
    path.write_text(json.dumps(conf))
    return path


@pytest.mark.parametrize(
    "command",
    [
        ["estop"],
        ["send", '{"plan": [{"action": "navigate_to", "target": "kitchen"}]}'],
        ["goal", "0123"],
        ["cancel"],
        ["reset", "--token-file", "/nonexistent"],
        ["status"],
        ["world", "move", "red_cup", "1", "1"],
        ["world", "scene"],
        ["mode"],
        ["pending"],
        ["approve", "0123", "--token-file", "TOKEN"],
        ["incidents"],
        ["incidents", "show", "1"],
        ["ask", "bring me the red cup"],
    ],
)
@pytest.mark.parametrize("as_json", [False, True])
def test_a_command_whose_router_is_down_says_so_and_exits_3(
    router_down: Path, command: list[str], as_json: bool
) -> None:
    token = router_down.with_name("operator.token")  # one that reads: the session is what fails
    token.write_text("ab" * 24 + "\n")
    token.chmod(0o600)
    command = [str(token) if arg == "TOKEN" else arg for arg in command]
    args = ["--zenoh-config", str(router_down), *command, *(["--json"] if as_json else [])]
    result = CliRunner().invoke(cli.app, args)
    assert isinstance(result.exception, SystemExit) and result.exit_code == 3, (result.exception, result.output)
    said = result.stdout + result.stderr
    assert "Traceback" not in said and "cannot open a Zenoh session" in said, said
    if as_json:
        document = json.loads(result.stdout)
        assert document["status"] == "unreachable" and "Unable to connect" in document["reason"], document


def test_a_health_probe_whose_router_is_down_is_one_json_object(router_down: Path) -> None:
    result = CliRunner().invoke(cli.app, ["--zenoh-config", str(router_down), "status", "--check", "--json"])
    assert result.exit_code == 3, result.output
    report = json.loads(result.stdout)
    assert report["ok"] is False and "cannot open a Zenoh session" in report["problems"][0], report


def test_world_scene_json_without_a_resolver_is_one_object() -> None:
    args = ["--base-port", str(free_ports(9)), "world", "scene", "--json"]
    result = CliRunner().invoke(cli.app, args)
    assert result.exit_code == 3, result.output
    document = json.loads(result.stdout)
    assert document["status"] == "unreachable", document
    assert document["error"]["kind"] == "unavailable" and "no resolver" in document["error"]["message"], document


def children(pid: int) -> set[int]:
    """The processes whose parent is `pid` now."""
    found = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rpartition(")")[2].split()[1]) == pid:
                found.add(int(entry.name))
    return found


def running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.fixture
def started() -> Iterator[set[int]]:
    """Pids a test saw started; any still running at its end is killed."""
    pids: set[int] = set()
    yield pids
    for pid in pids:
        if running(pid):
            os.kill(pid, signal.SIGKILL)


def test_up_gives_up_on_a_router_that_is_down_at_its_timeout_and_stops_the_services(
    tmp_path: Path, started: set[int]
) -> None:
    router = deployment.RouterAddress.parse(f"127.0.0.1:{free_ports(1)}")
    deployment.init(tmp_path / "deploy", ["r1"], router=router)
    up = [sys.executable, "-m", "tether", "up", "--deploy", str(tmp_path / "deploy"), "--robot", "r1"]
    up += ["--only", "parser", "--timeout", "2", "--log-dir", str(tmp_path / "logs")]
    proc = subprocess.Popen(up, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    started.add(proc.pid)
    # 2 s for the router, up to 10 s for the parser to stop before it is killed, and some to spare.
    deadline = time.monotonic() + 40.0
    while proc.poll() is None and time.monotonic() < deadline:
        started.update(children(proc.pid))
        time.sleep(0.05)
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
    said = proc.communicate()[0].decode()
    assert proc.returncode is not None and proc.returncode >= 0, f"still waiting after 40 s (--timeout 2): {said}"
    assert proc.returncode == 1 and "no Zenoh session within 2 s" in said, said
    assert "the services were stopped" in said and "Traceback" not in said, said
    assert len(started) > 1, "tether up started no service"
    assert not [pid for pid in started if running(pid)], "a service tether up started is still running"


@pytest.mark.parametrize(
    ("args", "reason"),
    [
        (["x", "--format", "foo"], "--format must be auto, json, yaml or text, not 'foo'"),
        # A regular file that cannot be read (EIO at offset 0), as a disk error or a lost mount would be.
        (["/proc/self/mem"], "cannot read the plan file /proc/self/mem"),
    ],
)
def test_send_refuses_bad_usage_with_one_json_object_and_exit_2(args: list[str], reason: str) -> None:
    result = CliRunner().invoke(cli.app, ["send", *args, "--json"])
    assert isinstance(result.exception, SystemExit) and result.exit_code == 2, (result.exception, result.output)
    document = json.loads(result.stdout)
    assert document["status"] == "rejected" and document["reason"].startswith(reason), document


def test_a_zenoh_config_zenoh_cannot_use_is_one_error_line_for_commands_and_services(tmp_path: Path) -> None:
    """A wrong mode in a hand-edited operator.json5 or service config: a traceback before."""
    path = tmp_path / "operator.json5"
    path.write_text('{mode: "bogus"}')
    result = CliRunner().invoke(cli.app, ["--zenoh-config", str(path), "status", "--json"])
    assert result.exit_code == 2, result.output
    document = json.loads(result.stdout)
    assert document["status"] == "error" and f"Zenoh config file {path} cannot be used" in document["reason"]
    env = {**os.environ, "TETHER_ZENOH_CONFIG": str(path)}
    service = [sys.executable, "-m", "tether", "run", "parser"]
    done = subprocess.run(service, cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and f"error: Zenoh config file {path} cannot be used" in done.stderr
