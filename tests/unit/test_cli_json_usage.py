"""A usage error click finds before a command runs (a bad option value, an unknown option, a missing
argument or option value) is, when the command was given --json, one JSON object on stdout in that
command's shape of an error, exit 2; without --json, typer's box on stderr as ever. Real runs of
`python -m tether`, each failing before it would open a Zenoh session."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]


def tether(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "COLUMNS": "100", "NO_COLOR": "1"}
    return subprocess.run(
        [sys.executable, "-m", "tether", *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60
    )


def one_object(run: subprocess.CompletedProcess[str]) -> dict[str, Any]:
    """The one JSON object a run printed on stdout, and nothing else there."""
    lines = run.stdout.splitlines()
    assert len(lines) == 1, f"stdout: {run.stdout!r}\nstderr: {run.stderr}"
    document = json.loads(lines[0])
    assert isinstance(document, dict)
    return document


def refused(message: str) -> dict[str, Any]:
    """The world commands' refusal: the simulator's ServiceError, kind invalid_request."""
    error = {"type": "error", "kind": "invalid_request", "message": message, "stage": None, "step": None}
    return {"status": "refused", "error": {**error, "candidates": [], "line": None, "column": None}}


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (
            ["send", "--json", "--timeout", "abc", "x"],
            {
                "status": "rejected",
                "stage": None,
                "reason": "Invalid value for '--timeout': 'abc' is not a valid float.",
                "steps": [],
            },
        ),
        (
            ["send", "x", "--json", "--no-such-flag"],
            {"status": "rejected", "stage": None, "reason": "No such option: --no-such-flag", "steps": []},
        ),
        (
            # The unknown option first: the --json after it still counts.
            ["send", "--no-such-flag", "--json", "x"],
            {"status": "rejected", "stage": None, "reason": "No such option: --no-such-flag", "steps": []},
        ),
        (["send", "--json"], {"status": "rejected", "stage": None, "reason": "Missing argument 'plan'.", "steps": []}),
        (
            # click's error for an option's value missing at the end of the line has no command context.
            ["send", "--json", "x", "--timeout"],
            {"status": "rejected", "stage": None, "reason": "Option '--timeout' requires an argument.", "steps": []},
        ),
        (
            ["view", "--json", "--port", "notaport"],
            {"ok": False, "error": "Invalid value for '--port': 'notaport' is not a valid int range."},
        ),
        (
            ["teleop", "--json", "--scale", "nan"],
            {"ended": "error", "error": "Invalid value for '--scale': nan is not a number"},
        ),
        (["cancel", "--json", "a", "b"], {"status": "error", "reason": "Got unexpected extra argument(s) (b)"}),
        (
            ["reset", "--json", "--tokn"],
            {"status": "error", "message": "No such option: --tokn (Possible options: --json, --token-file)"},
        ),
        (
            ["status", "--json", "--service"],
            {"ok": False, "alive": [], "heartbeat": False, "problems": ["Option '--service' requires an argument."]},
        ),
        (
            ["world", "move", "red_cup", "1", "two", "--json"],
            refused("Invalid value for 'y': 'two' is not a valid float."),
        ),
        (["pending", "--json", "--all"], {"ok": False, "error": "No such option: --all"}),
        (["incidents", "show", "--json", "--bogus", "1"], {"ok": False, "error": "No such option: --bogus"}),
        (
            # --json of the incidents group itself (it lists them).
            ["incidents", "--json", "--limit", "0"],
            {"ok": False, "error": "Invalid value for '--limit': 0 is not in the range 1<=x<=1000."},
        ),
        (["deploy", "init", "--json"], {"error": "Missing argument 'directory'."}),
        (["--robot", "r2", "inspect", "--json"], {"error": "Missing argument 'FILE'."}),
    ],
)
def test_a_usage_error_with_json_is_one_object_on_stdout(args: list[str], expected: dict[str, Any]) -> None:
    run = tether(*args)
    assert run.returncode == 2, run.stderr
    assert one_object(run) == expected
    assert run.stderr == ""


@pytest.mark.parametrize(
    "args",
    [
        ["send", "--timeout", "abc", "x"],
        ["view", "--port", "notaport"],
        ["send", "x", "--timeout"],
        # --json that is not the command's option: the plan text after `--`, another option's value,
        # the option of the group before the command, the shared flags' value, or no known command.
        ["send", "--timeout", "abc", "--", "--json"],
        ["send", "--", "--json", "--timeout", "abc"],
        ["send", "--format", "--json", "x", "--timeout", "abc"],
        ["incidents", "--json", "show", "--bogus", "1"],
        ["--robot", "send", "--json"],
        ["sendd", "--json"],
        ["send", "--json=yes", "x"],
    ],
)
def test_a_usage_error_without_json_is_typers_box_on_stderr(args: list[str]) -> None:
    run = tether(*args)
    assert run.returncode == 2, run.stderr
    assert run.stdout == ""
    assert "Error" in run.stderr and "╭" in run.stderr, run.stderr


def test_a_commands_own_checks_keep_their_objects_and_codes() -> None:
    run = tether("send", "--json", "--format", "xml", "x")
    assert run.returncode == 2, run.stderr
    why = "--format must be auto, json, yaml or text, not 'xml'"
    assert one_object(run) == {"status": "rejected", "stage": None, "reason": why, "steps": []}
    helped = tether("send", "--json", "--help")
    assert helped.returncode == 0 and "Send a plan to the executor" in helped.stdout, helped.stderr


@pytest.mark.parametrize(
    ("args", "why"),
    [
        (["--service", "sim"], "--service goes with --check"),
        (["--check", "--service", "nope"], "unknown service nope; services are "),
    ],
)
def test_status_says_its_own_usage_errors_as_one_object_with_json(args: list[str], why: str) -> None:
    run = tether("status", "--json", *args)
    assert run.returncode == 2, run.stderr
    document = one_object(run)
    assert document["ok"] is False and document["alive"] == [] and document["heartbeat"] is False
    [problem] = document["problems"]
    assert problem.startswith(why)
    said = tether("status", *args)
    assert said.returncode == 2 and said.stdout == ""
    assert "error:" in said.stderr and why in " ".join(said.stderr.split())
