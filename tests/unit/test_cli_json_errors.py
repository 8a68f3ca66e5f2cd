"""A command given --json says an error of its own (a missing or damaged recording, a bad policy,
world, key or token file) as one JSON object on stdout, in its shape of an error, with the exit code
it has without --json; without --json, the same words on stderr as ever. Real runs through the CLI,
each failing before it would open a Zenoh session."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner, Result

from services.recorder.mcapfile import Provenance, Recording, SourceFile
from services.safety.policyfile import DEFAULT_POLICY
from services.worldmodel import world_path
from tether.cli import app

ROBOT = "r1"


def run(*args: str) -> Result:
    return CliRunner().invoke(app, ["--robot", ROBOT, *args], env={"COLUMNS": "200", "NO_COLOR": "1"})


def one_object(result: Result) -> dict[str, Any]:
    """The one JSON object a run printed on stdout, and nothing else there."""
    lines = result.stdout.splitlines()
    assert len(lines) == 1, f"stdout: {result.stdout!r}\nstderr: {result.stderr}"
    document = json.loads(lines[0])
    assert isinstance(document, dict)
    return document


def words(text: str) -> str:
    return " ".join(text.split())


def recording(path: Path, world: bool = True) -> Path:
    """A whole recording of one message, with the bundled policy kept, and the world unless not `world`."""
    kept = Provenance(
        ROBOT,
        world=SourceFile.read(world_path("household")) if world else None,
        policy=SourceFile.read(DEFAULT_POLICY),
    )
    made = Recording(path, ROBOT, provenance=kept)
    made.record(f"tether/{ROBOT}/odom", b'{"x": 0}')
    made.finish()
    return path


def cut(path: Path) -> Path:
    """A recording cut within its first records: no reader can take anything from it."""
    whole = recording(path.with_suffix(".whole.mcap"))
    path.write_bytes(whole.read_bytes()[:12])
    return path


# Each case: the command's arguments (a {tmp} in them is the test's folder), what makes a file, and a
# word of its error.
RECORDING_ERRORS = [
    (["{tmp}/missing.mcap"], None, "no such file"),
    (["{tmp}/garbage.mcap"], lambda tmp: (tmp / "garbage.mcap").write_bytes(b"garbage"), "not an MCAP recording"),
    (["{tmp}/cut.mcap"], lambda tmp: cut(tmp / "cut.mcap"), "ends early"),
    (["--robot-key", "{tmp}/no-key", "{tmp}/r.mcap"], lambda tmp: recording(tmp / "r.mcap"), "--robot-key"),
]
RECHECK_ERRORS = [
    *RECORDING_ERRORS,
    (["--policy", "{tmp}/nope.yaml", "{tmp}/r.mcap"], lambda tmp: recording(tmp / "r.mcap"), "nope.yaml"),
    (
        ["--policy", "{tmp}/bad.yaml", "{tmp}/r.mcap"],
        lambda tmp: (recording(tmp / "r.mcap"), (tmp / "bad.yaml").write_text("limits: [\n")),
        "bad.yaml",
    ),
    (["{tmp}/r.mcap"], lambda tmp: recording(tmp / "r.mcap", world=False), "--world"),
    (["--world", "no_such_world", "{tmp}/r.mcap"], lambda tmp: recording(tmp / "r.mcap", world=False), "no_such_world"),
]
INSPECT_ERRORS = [
    *RECORDING_ERRORS,
    (["--keys", "a/**b", "{tmp}/r.mcap"], lambda tmp: recording(tmp / "r.mcap"), "--keys"),
    (["--png", "{tmp}/no/such/folder/map.png", "{tmp}/r.mcap"], lambda tmp: recording(tmp / "r.mcap"), "map"),
]


def prepared(tmp: Path, args: list[str], make: Any) -> list[str]:
    if make is not None:
        make(tmp)
    return [arg.replace("{tmp}", str(tmp)) for arg in args]


def said_both_ways(command: str, args: list[str], word: str) -> None:
    """`command` with --json: {"error"} alone on stdout, exit 2; without: the same error on stderr."""
    given = one_object(result := run(command, "--json", *args))
    assert result.exit_code == 2, result.output
    assert list(given) == ["error"] and word in given["error"], given
    plain = run(command, *args)
    assert plain.exit_code == 2 and not plain.stdout, plain.output
    assert words(f"error: {given['error']}") in words(plain.stderr), plain.stderr


@pytest.mark.parametrize(("args", "make", "word"), RECHECK_ERRORS)
def test_recheck_says_its_error_as_one_json_object(tmp_path: Path, args: list[str], make: Any, word: str) -> None:
    said_both_ways("recheck", prepared(tmp_path, args, make), word)


@pytest.mark.parametrize(("args", "make", "word"), INSPECT_ERRORS)
def test_inspect_says_its_error_as_one_json_object(tmp_path: Path, args: list[str], make: Any, word: str) -> None:
    said_both_ways("inspect", prepared(tmp_path, args, make), word)


@pytest.mark.parametrize(
    "command",
    [
        ["mode", "autonomous"],
        ["approve", "g1"],
        ["deny", "g1"],
        ["incidents", "forget", "1", "--reason", "test"],
        ["incidents", "clear", "1", "--reason", "test"],
    ],
)
def test_a_token_file_that_is_not_text_is_refused_as_an_error(tmp_path: Path, command: list[str]) -> None:
    """Refused before any Zenoh call, as an unreadable one is: {"ok": false, "error"}, exit 2; not a traceback."""
    token = tmp_path / "operator-token"
    token.write_bytes(b"\xd0\xff binary \x00")
    given = one_object(result := run(*command, "--token-file", str(token), "--json"))
    assert result.exit_code == 2, result.output
    assert given["ok"] is False and "cannot read the operator token" in given["error"], given
    plain = run(*command, "--token-file", str(token))
    assert plain.exit_code == 2 and not plain.stdout, plain.output
    assert "error: cannot read the operator token" in words(plain.stderr), plain.stderr
