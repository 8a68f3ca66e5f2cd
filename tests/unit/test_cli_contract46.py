"""The CLI contract for durations and speeds: a --timeout that is not more than 0 and at most a week
(negative, zero, NaN, huge) or a demo --sim-speed the sim would refuse is a usage error, exit 2 (with
--json one object), said before anything is sent or started. Before, `send` sent the plan and then
gave up on it (exit 3 with the robot moving) or crashed with a traceback; `up` started services it
could not wait for, or crashed; `demo` started the stack for the sim to refuse its config. Real runs
of `python -m tether`, on a robot name and ports of their own."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.sessions import free_ports
from tether import deployment

ROOT = Path(__file__).resolve().parents[2]


def tether(*args: str) -> subprocess.CompletedProcess[str]:
    """`tether ARGS` on a robot and ports of this test's own; its process group killed if it hangs."""
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1"}
    command = [sys.executable, "-m", "tether", "--robot", "contract46", "--base-port", str(free_ports(10)), *args]
    proc = subprocess.Popen(
        command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
    return subprocess.CompletedProcess(command, proc.returncode, out, err)


BAD_TIMEOUTS = ["-1", "0", "nan", "1e308"]
PLAN = '{"plan": [{"action": "navigate_to", "target": "kitchen"}]}'


@pytest.mark.parametrize("timeout", BAD_TIMEOUTS)
def test_send_refuses_a_timeout_out_of_range_before_sending_the_plan(timeout: str) -> None:
    run = tether("send", PLAN, "--wait", "--json", "--timeout", timeout)
    assert run.returncode == 2, run
    assert "Traceback" not in run.stderr, run.stderr
    document = json.loads(run.stdout)
    assert document["status"] == "rejected" and document["stage"] is None, document
    assert "'--timeout'" in document["reason"] and "at most 604800 seconds" in document["reason"], document


@pytest.mark.parametrize("timeout", BAD_TIMEOUTS)
def test_ask_refuses_a_timeout_out_of_range_before_asking(timeout: str) -> None:
    # As send's, checked before anything is asked: send's sent its plan, then gave up at once.
    run = tether("ask", "go to the kitchen", "--json", "--timeout", timeout)
    assert run.returncode == 2, run
    assert "Traceback" not in run.stderr, run.stderr
    document = json.loads(run.stdout)
    assert document["status"] == "error" and "at most 604800 seconds" in document["reason"], document


@pytest.mark.parametrize("timeout", ["-1", "nan"])
def test_up_refuses_a_timeout_out_of_range_before_starting_a_service(tmp_path: Path, timeout: str) -> None:
    run = tether("up", "--only", "parser", "--timeout", timeout, "--log-dir", str(tmp_path / "logs"))
    assert run.returncode == 2, run
    assert "Invalid value for '--timeout'" in run.stderr and "Traceback" not in run.stderr, run.stderr
    assert not (tmp_path / "logs").exists(), "a service was started"


def test_up_with_a_deployment_refuses_a_nan_timeout_without_a_traceback(tmp_path: Path) -> None:
    router = deployment.RouterAddress.parse(f"127.0.0.1:{free_ports(1)}")
    deployment.init(tmp_path / "deploy", ["r1"], router=router)
    run = tether("up", "--deploy", str(tmp_path / "deploy"), "--robot", "r1", "--only", "parser", "--timeout", "nan")
    assert run.returncode == 2, run
    assert "Invalid value for '--timeout'" in run.stderr and "Traceback" not in run.stderr, run.stderr


@pytest.mark.parametrize(("option", "value"), [("--sim-speed", "nan"), ("--sim-speed", "-1"), ("--timeout", "nan")])
def test_demo_refuses_a_value_out_of_range_before_starting_a_service(tmp_path: Path, option: str, value: str) -> None:
    run = tether("demo", option, value, "--log-dir", str(tmp_path / "logs"), "--recordings", str(tmp_path / "rec"))
    assert run.returncode == 2, run
    assert f"Invalid value for '{option}'" in run.stderr and "Traceback" not in run.stderr, run.stderr
    assert not (tmp_path / "logs").exists(), "a service was started"


@pytest.mark.parametrize(
    ("args", "option"),
    [(["--near", "5000", "1"], "--near"), (["--near", "1", "nan"], "--near"), (["--radius", "nan"], "--radius")],
)
def test_incidents_names_the_option_whose_value_is_out_of_range(args: list[str], option: str) -> None:
    run = tether("incidents", "--json", *args)
    assert run.returncode == 2, run
    document = json.loads(run.stdout)
    assert document["ok"] is False and document["error"].startswith(f"{option}: "), document


# A byte that is not UTF-8 in an argument (Python keeps it as the surrogate "\udcff") was a traceback
# when encoded into the message sent; it is a usage error naming the argument.
NOT_UTF8 = "go\udcff"


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["send", NOT_UTF8, "--dry-run"], "'plan'"),
        (["goal", NOT_UTF8], "'goal_id'"),
        (["cancel", NOT_UTF8], "'goal_id'"),
        (["estop", "--reason", NOT_UTF8], "'--reason'"),
        (["world", "move", NOT_UTF8, "1", "1"], "'ID'"),
    ],
)
def test_an_argument_that_is_not_utf8_is_a_usage_error_naming_it(args: list[str], named: str) -> None:
    run = tether(*args, "--json")
    assert run.returncode == 2, run
    assert "Traceback" not in run.stderr, run.stderr
    assert f"Invalid value for {named}: not UTF-8 text (a byte at character 3)" in run.stdout, run.stdout
    json.loads(run.stdout)


def test_send_reads_a_plan_on_stdin_that_is_not_utf8_without_a_traceback() -> None:
    env = {**os.environ, "NO_COLOR": "1"}
    command = [sys.executable, "-m", "tether", "--robot", "contract46", "--base-port", str(free_ports(10))]
    run = subprocess.run(
        [*command, "send", "-", "--json"],
        input=b"go to the kitchen\xff",
        cwd=ROOT,
        env=env,
        capture_output=True,
        timeout=60,
    )
    assert b"Traceback" not in run.stderr, run.stderr.decode(errors="replace")
    # Nothing runs here: the plan read, the executor is found missing.
    assert run.returncode == 3 and json.loads(run.stdout)["status"] == "unreachable", run
