"""A flood of undecodable messages, with two real Zenoh sessions in one process: one log line and a count."""

from __future__ import annotations

import logging
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from schemas import keys
from schemas.common import ErrorKind, ServiceError
from services.errors import CallError
from services.runtime import Node, NodeSettings
from tests.sessions import free_port

ROOT = Path(__file__).resolve().parents[2]

FLOOD = 1000


def test_a_flood_of_garbage_is_one_line_and_a_count(caplog: pytest.LogCaptureFixture) -> None:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    heard: list[object] = []
    reported: list[tuple[str, str, int]] = []
    with Node("sim", settings) as listener, Node("attacker", settings) as attacker:
        listener.on_undecodable = lambda key, line, count: reported.append((key, line, count))
        listener.subscribe(keys.ODOM, heard.append)
        listener.serve(keys.ROBOT_DIAGNOSTICS, lambda _req: pytest.fail("a garbage request reached the handler"))
        listener.declare_alive()
        assert not attacker.wait_alive(["sim"], 10.0)
        key = keys.ODOM.key(settings.robot)
        with caplog.at_level(logging.WARNING, logger="services.runtime"):
            # Until the subscriber is matched every put is lost: send until the first is counted.
            deadline = time.monotonic() + 10.0
            while listener.undecodable.total == 0:
                assert time.monotonic() < deadline, "the garbage never arrived"
                attacker.session.put(key, b"\xff not json")
                time.sleep(0.01)  # pacing until the subscriber is matched
            first = listener.undecodable.total
            publisher = attacker.session.declare_publisher(key)
            for _ in range(FLOOD):
                publisher.put(b"\xff not json")
            deadline = time.monotonic() + 10.0
            while listener.undecodable.total < first + FLOOD:
                assert time.monotonic() < deadline, f"{listener.undecodable.total - first} of {FLOOD} arrived"
                time.sleep(0.01)  # polling the count with a deadline
            for _ in range(3):
                with pytest.raises(CallError) as refused:
                    # bytes go out as a JSON string: not the request's object
                    attacker.call(keys.ROBOT_DIAGNOSTICS, b"\xff")  # type: ignore[arg-type]
                assert isinstance(refused.value.error, ServiceError)
                assert refused.value.error.kind is ErrorKind.INVALID_REQUEST
    lines = [r.getMessage() for r in caplog.records if r.name == "services.runtime"]
    assert len(lines) == 2, lines
    assert lines[0].startswith(f"undecodable messages dropped on {key}: sample:")
    assert lines[1].startswith(f"undecodable messages dropped on {keys.ROBOT_DIAGNOSTICS.key(settings.robot)}")
    assert listener.undecodable.count(key) == listener.undecodable.total - 3 - 1
    assert not heard
    # One report per line, for a service to publish as an event (safety does): the first, with its count.
    assert [(k, c) for k, _, c in reported] == [(key, 1), (keys.ROBOT_DIAGNOSTICS.key(settings.robot), 1)]


def test_a_services_log_escapes_control_characters_others_wrote() -> None:
    """An e-stop's reason (anyone may publish one) was logged raw: its ESC sequences retitled and
    repainted the terminal that showed safety's log. Newlines and tabs (tracebacks) stay."""
    code = (
        "import logging; from services.runtime import configure_logging; configure_logging(); "
        "logging.getLogger('safety').warning('E-STOP latched by %s: %s', 'agent', "
        "'x\\x1b]0;pwned\\x07\\x9b2J\\nnext\\tcol')"
    )
    child = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert "x\\x1b]0;pwned\\x07\\x9b2J\nnext\tcol" in child.stderr
    assert not any(ch in child.stderr for ch in "\x1b\x07\x9b")
