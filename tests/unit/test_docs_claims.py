"""Numbers the docs state, read from the constants that decide them: a constant changed without its
sentence (or a sentence edited away from the code) fails here, naming the document."""

from __future__ import annotations

from pathlib import Path

import pytest

from schemas.incidents import MAX_LISTED
from schemas.planner import MAX_REQUEST_CHARS
from services import robotlink, robotrules, runtime
from services.actionlib import MAX_RESULTS, RESULT_RETENTION
from services.safety.operator import MAX_TOKEN_BYTES
from tether import client, teleop

ROOT = Path(__file__).resolve().parents[2]

CLAIMS = [
    ("docs/robot.md", f"the last {robotlink.MAX_SESSIONS} superseded are remembered"),
    ("docs/architecture.md", f"at most {MAX_RESULTS} of them"),
    (
        "docs/architecture.md",
        f"at most {runtime.QUERY_WORKERS} handlers run at once and {runtime.QUERY_BACKLOG} more queries wait",
    ),
    ("services/safety/README.md", f"its `changed` lists at most {MAX_LISTED} of their ids"),
    ("services/safety/README.md", f"is over {MAX_TOKEN_BYTES // 1024} KiB is no token"),
    ("services/sim/README.md", f"(within `PREEMPT_TIMEOUT`, {robotrules.PREEMPT_TIMEOUT:g} s,"),
    ("README.md", f"over {MAX_REQUEST_CHARS} characters, not UTF-8"),
    ("README.md", f"waits up to {client.CANCEL_WAIT:g} s for its end"),
    ("README.md", f"asked again for up to {client.RESULT_GONE:g} s"),
    ("README.md", f"ended over {RESULT_RETENTION / 60:g} minutes ago or before {MAX_RESULTS} newer ones ended"),
    ("README.md", f"no heartbeat from safety within {teleop.HEARTBEAT_WAIT:g} s"),
]


def words(path: str) -> str:
    """The document with its line breaks and runs of spaces as single spaces, as a reader sees it."""
    return " ".join((ROOT / path).read_text().split())


@pytest.mark.parametrize(("path", "claim"), CLAIMS)
def test_the_docs_state_the_number_the_code_uses(path: str, claim: str) -> None:
    assert claim in words(path), f"{path} no longer says {claim!r}: bring the sentence and the constant together"
