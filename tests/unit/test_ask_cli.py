"""`tether ask` refuses a request it cannot ask before asking anything: exit 2, and with --json the
reason as one JSON object on stdout (as its other errors are), so a script reading it is not left
with nothing to parse."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from schemas.planner import MAX_REQUEST_CHARS
from tether.cli import app


def bad_config(tmp_path: Path) -> str:
    config = tmp_path / "bad.toml"
    config.write_text("[planner]\nbogus = 1\n")
    return str(config)


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["   "], "the request must be 1 to"),
        (["x" * (MAX_REQUEST_CHARS + 1)], f"not {MAX_REQUEST_CHARS + 1}"),
        (["bring me the cup", "--config", "BAD"], "bogus"),
    ],
)
def test_a_request_that_cannot_be_asked_is_refused_in_json_with_json(
    tmp_path: Path, args: list[str], said: str
) -> None:
    args = [bad_config(tmp_path) if a == "BAD" else a for a in args]
    result = CliRunner().invoke(app, ["ask", "--json", *args])
    assert result.exit_code == 2, result.output
    document = json.loads(result.stdout)
    assert document["status"] == "error" and said in document["reason"], document
    plain = CliRunner().invoke(app, ["ask", *args])
    assert plain.exit_code == 2 and not plain.stdout
    assert "error:" in plain.stderr and said in " ".join(plain.stderr.split())
