"""`--json` of the commands that act (estop, reset, cancel, world move) against real services: one
object on stdout, the exit codes their help gives, and what a service or a person wrote printed as written."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from tests.integration.conftest import Stack, start_stack, stop_stack, tether_cli

HOSTILE = "[sim] halt [/] now"


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    """The simulator, safety and the executor: all these commands talk to."""
    s = start_stack(tmp_path_factory.mktemp("cli_json"), realtime_factor=4.0, services=("sim", "safety", "executor"))
    try:
        yield s
    finally:
        stop_stack(s)


Outcome = tuple[int, dict[str, Any], subprocess.CompletedProcess[str]]


def outcome(stack: Stack, *args: str) -> Outcome:
    """The exit code and the one JSON object on stdout of `tether ARGS --json`."""
    ran = tether_cli(stack, *args, "--json")
    return ran.returncode, json.loads(ran.stdout), ran


def outcomes(stack: Stack, *commands: tuple[str, ...]) -> list[Outcome]:
    """`outcome` of each command, run at once (each is a Python process starting)."""
    with ThreadPoolExecutor(len(commands)) as pool:
        return list(pool.map(lambda args: outcome(stack, *args), commands))


def test_estop_and_reset_say_their_outcome_as_json_and_print_a_reason_as_written(stack: Stack, tmp_path: Path) -> None:
    code, latched, ran = outcome(stack, "estop", "--reason", HOSTILE)
    assert code == 0, ran.stderr
    assert (latched["status"], latched["source"]) == ("latched", "operator"), latched
    assert latched["reason"].startswith(HOSTILE), latched

    wrong = tmp_path / "wrong.token"
    wrong.write_text("not the token\n")
    (code, refused, ran), (code_, missing, ran_) = outcomes(
        stack, ("reset", "--token-file", str(wrong)), ("reset", "--token-file", str(tmp_path / "none.token"))
    )
    assert (code, refused["status"]) == (2, "refused"), ran.stdout + ran.stderr
    assert (code_, missing["status"]) == (2, "no_token"), ran_.stdout + ran_.stderr

    # Without --json: in words, the reason as written (rich markup would have eaten `[sim]` and failed on `[/]`).
    status = tether_cli(stack, "status")
    assert f"LATCHED by operator: {HOSTILE}" in " ".join(status.stderr.split()), status.stderr

    code, reset, ran = outcome(stack, "reset", "--token-file", str(stack.token_file))
    assert (code, reset["status"]) == (0, "reset"), ran.stdout + ran.stderr
    assert "reset by" in reset["message"]


def test_cancel_and_world_move_say_their_outcome_as_json(stack: Stack) -> None:
    nobody = ("--base-port", "1100", "--robot", "nobody")
    cancel, move, unknown, no_sim = outcomes(
        stack,
        ("cancel",),
        ("world", "move", "apple", "7.0", "1.5"),
        ("world", "move", "unicorn", "7.0", "1.5"),
        (*nobody, "world", "move", "apple", "7", "1"),
    )
    code, nothing, ran = cancel
    assert (code, nothing["status"], nothing["goal_id"]) == (0, "nothing_to_cancel", "all"), ran.stdout + ran.stderr
    assert nothing["reason"], nothing

    code, moved, ran = move
    assert (code, moved["status"], moved["id"]) == (0, "moved", "apple"), ran.stdout + ran.stderr
    assert (moved["position"]["x"], moved["position"]["y"]) == pytest.approx((7.0, 1.5), abs=0.05), moved

    code, refused, ran = unknown
    assert (code, refused["status"], refused["error"]["kind"]) == (2, "refused", "invalid_request"), ran.stdout
    assert "red_cup" in refused["error"]["candidates"], refused

    code, unreachable, ran = no_sim
    assert (code, unreachable["status"]) == (3, "unreachable"), ran.stdout + ran.stderr
