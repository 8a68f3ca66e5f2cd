"""Hostile peers against the transport core: garbage on made-up wildcard keys, a replay after the
robot's clock stepped back. The first with two real Zenoh sessions in one process, the second pure."""

from __future__ import annotations

import itertools
import logging
import time
import uuid
from collections.abc import Iterator

import pytest

from schemas import keys
from schemas.common import ErrorKind
from schemas.safety import EStop, EstopSource
from schemas.world import Empty
from services.errors import CallError
from services.robotlink import MAX_SKEW, REPLAYED, Signer, Verifier
from services.runtime import Node, NodeSettings
from tests.sessions import free_port

KEY = bytes(range(32))
ROBOT = "robot1"


def made_up_keys(key: str) -> Iterator[str]:
    """Wildcard key expressions, each its own, all reaching a subscriber of `key` (`a/b/odom` -> `a/b/o$*dom`...)."""
    head, _, word = key.rpartition("/")
    for gaps in itertools.product(("", "$*"), repeat=len(word) - 1):
        if any(gaps):
            yield f"{head}/" + "".join(c + g for c, g in zip(word, (*gaps, ""), strict=True))


def test_garbage_on_made_up_wildcard_keys_is_one_line_and_one_report(caplog: pytest.LogCaptureFixture) -> None:
    """Zenoh hands a subscriber each put on a wildcard expression that reaches it, under that expression:
    counted by the expression, every made-up one was a warning of its own and a report (safety publishes
    each as an event), a line and an event per message for a peer sending garbage."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    heard: list[object] = []
    reported: list[tuple[str, str, int]] = []
    key = keys.ODOM.key(settings.robot)
    made_up = list(made_up_keys(key))
    assert len(made_up) == 2**3 - 1
    with Node("sim", settings) as listener, Node("attacker", settings) as attacker:
        listener.on_undecodable = lambda k, line, count: reported.append((k, line, count))
        listener.subscribe(keys.ODOM, heard.append)
        listener.declare_alive()
        assert not attacker.wait_alive(["sim"], 10.0)
        with caplog.at_level(logging.WARNING, logger="services.runtime"):
            deadline = time.monotonic() + 10.0
            while listener.undecodable.total == 0:  # until the subscriber is matched every put is lost
                assert time.monotonic() < deadline, "the garbage never arrived"
                attacker.session.put(key, b"\xff not json")
                time.sleep(0.01)  # pacing until the subscriber is matched
            first = listener.undecodable.total
            for key_expr in made_up:
                attacker.session.put(key_expr, b"\xff not json")
            deadline = time.monotonic() + 10.0
            while listener.undecodable.total < first + len(made_up):
                assert time.monotonic() < deadline, f"{listener.undecodable.total - first} of {len(made_up)} arrived"
                time.sleep(0.01)  # polling the count with a deadline
    lines = [r.getMessage() for r in caplog.records if r.name == "services.runtime"]
    assert len(lines) == 1, lines
    assert [(k, c) for k, _, c in reported] == [(key, 1)]
    assert not heard


class Clock:
    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def test_a_command_taken_before_the_robots_clock_stepped_back_is_still_a_replay() -> None:
    """A safety's session silent on a key for 2 x MAX_SKEW was forgotten there, counted on the robot's
    wall clock: once that clock stepped back (NTP) past the forgetting, a recorded twist of it was
    within the time window again, and taken a second time."""
    clock = Clock()
    verifier = Verifier(KEY, clock)
    safety = Signer(KEY, clock)
    cmd_vel, heartbeat = keys.ROBOT_CMD_VEL.key(ROBOT), keys.HEARTBEAT.key(ROBOT)
    recorded = safety.sign(cmd_vel, b"go")
    assert verifier.check(cmd_vel, b"go", recorded) is None
    clock.now += 2 * MAX_SKEW + 0.1
    assert verifier.check(heartbeat, b"beat", safety.sign(heartbeat, b"beat")) is None
    clock.now = 1001.0  # stepped back 3.1 s: the recorded twist is 1 s old again
    refusal = verifier.check(cmd_vel, b"go", recorded)
    assert refusal is not None and refusal.why == REPLAYED, refusal


@pytest.mark.parametrize("discovering", [True, False], ids=["just-opened", "settled"])
def test_a_call_or_publication_on_a_closed_node_is_a_call_error_or_dropped(discovering: bool) -> None:
    """A thread of a service still at work as it shut down (a plan's step asking safety): its call met
    Zenoh's "session closed", which no caller catches, in place of the CallError `call` promises; a
    publication in the session's first second (waiting for a subscriber) raised it too."""
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    node = Node("executor", settings)
    if not discovering:
        node._discovering_until = 0.0
    node.close()
    with pytest.raises(CallError) as cut:
        node.call(keys.ROBOT_DIAGNOSTICS, Empty(), timeout=1.0)
    assert cut.value.error.kind is ErrorKind.UNAVAILABLE
    assert "session closed" in cut.value.error.message
    node.publish(keys.ESTOP, EStop(source=EstopSource.EXECUTOR, reason="closed"))
