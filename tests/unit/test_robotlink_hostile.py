"""The robot link against a hostile peer and hostile key files: pure logic."""

from __future__ import annotations

import itertools
import os
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from schemas import keys
from services.robotlink import (
    NOT_SIGNED,
    REPLAYED,
    SUPERSEDED,
    WILDCARD,
    KeyFileError,
    LinkGuard,
    Signer,
    Verifier,
    read_key,
)

KEY = bytes(range(32))
ROBOT = "robot1"
CMD_VEL = keys.ROBOT_CMD_VEL.key(ROBOT)
HEARTBEAT = keys.HEARTBEAT.key(ROBOT)
SEND_GOAL = keys.ROBOT_NAVIGATE.send_goal.key(ROBOT)


class Clock:
    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def made_up_heartbeat_keys() -> Iterator[str]:
    """Key expressions, each its own, that all reach a subscriber of the heartbeat (Zenoh delivers a put
    on a wildcard expression to every subscriber it intersects): `$*` between any letters."""
    word = "heartbeat"
    for gaps in itertools.product(("", "$*"), repeat=len(word) - 1):
        chunk = "".join(letter + gap for letter, gap in zip(word, (*gaps, ""), strict=True))
        yield f"tether/{ROBOT}/safety/{chunk}"
        yield f"**/{chunk}"


def test_refusals_on_made_up_wildcard_keys_are_one_kind_logged_once(caplog: pytest.LogCaptureFixture) -> None:
    """A peer cycling through made-up key expressions got a log line for each message, and filled
    robot/diagnostics with its own words."""
    clock = Clock()
    reported: list[str] = []
    guard = LinkGuard(Verifier(KEY, clock), reported.append, wall_clock=clock, clock=clock)
    made_up = list(itertools.islice(made_up_heartbeat_keys(), 2, None))  # not the concrete key itself
    assert len(set(made_up)) > 500
    with caplog.at_level("WARNING", logger="services.robotlink"):
        assert guard(CMD_VEL, b"{}", None) is not None
        for key_expr in made_up:
            assert guard(key_expr, b"{}", None) is not None
            clock.now += 0.001
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2, lines[:5]
    assert lines[1].startswith(f"messages refused as not from safety on {WILDCARD}: {NOT_SIGNED}")
    assert repr(made_up[0]) in lines[1], "the line names the key expression it came on"
    assert [text for text, _ in guard.problems(60.0)] == [
        f"refused {WILDCARD}: {NOT_SIGNED} ({len(made_up)} so far)",
        f"refused robot/cmd_vel: {NOT_SIGNED} (1 so far)",
    ]
    assert set(reported) == {f"refused {WILDCARD}: {NOT_SIGNED}", f"refused robot/cmd_vel: {NOT_SIGNED}"}


def test_a_wildcard_on_the_robot_name_is_counted_under_the_key_it_reached() -> None:
    clock = Clock()
    guard = LinkGuard(Verifier(KEY, clock), wall_clock=clock, clock=clock)
    assert guard("tether/*/robot/cmd_vel", b"{}", None) is not None
    assert [text for text, _ in guard.problems(60.0)] == [f"refused robot/cmd_vel: {NOT_SIGNED} (1 so far)"]


def test_a_key_file_that_is_not_text_is_refused_saying_why(tmp_path: Path) -> None:
    path = tmp_path / "robot.key"
    path.write_bytes(b"\xff\xfe" + b"ab" * 32)
    path.chmod(0o600)
    with pytest.raises(KeyFileError, match="not hex"):
        read_key(path)


def test_a_key_file_that_is_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path: Path) -> None:
    path = tmp_path / "robot.key"
    os.mkfifo(path, 0o600)
    raised: list[BaseException] = []

    def read() -> None:
        try:
            read_key(path)
        except BaseException as exc:
            raised.append(exc)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout=5.0)
    try:
        assert not reader.is_alive(), "reading the key blocked on the FIFO"
        assert len(raised) == 1 and isinstance(raised[0], KeyFileError), raised
        assert "not a regular file" in str(raised[0])
    finally:
        if reader.is_alive():  # let a blocked reader go: a writer opens and closes it
            os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))
            reader.join(timeout=5.0)


def test_a_key_file_far_too_long_to_be_a_key_is_refused_unread(tmp_path: Path) -> None:
    path = tmp_path / "robot.key"
    path.write_text("ab" * 32 + " " * 5000 + "\n")
    path.chmod(0o600)
    with pytest.raises(KeyFileError) as refused:
        read_key(path)
    assert str(refused.value) == f"robot key file {path}: more than 1024 bytes; not read"


def test_a_key_with_surrounding_whitespace_and_crlf_is_the_same_key(tmp_path: Path) -> None:
    path = tmp_path / "robot.key"
    path.write_bytes(b"  " + KEY.hex().encode() + b" \r\n")
    path.chmod(0o600)
    assert read_key(path) == KEY


def why(verifier: Verifier, key_expr: str, payload: bytes, attachment: bytes) -> str | None:
    refusal = verifier.check(key_expr, payload, attachment)
    return None if refusal is None else refusal.why


def test_once_a_restarted_safety_beats_nothing_its_predecessor_signed_is_taken() -> None:
    """A goal and a twist the old safety signed just before it died, held back on the way and delivered
    after the new one is beating: they ran, under a safety that never approved them."""
    clock = Clock()
    verifier = Verifier(KEY, clock)
    before = Signer(KEY, clock)
    assert why(verifier, HEARTBEAT, b"beat", before.sign(HEARTBEAT, b"beat")) is None
    taken = before.sign(CMD_VEL, b"went")
    assert why(verifier, CMD_VEL, b"went", taken) is None
    held_goal, held_twist = before.sign(SEND_GOAL, b"goal"), before.sign(CMD_VEL, b"go")
    clock.now += 0.8  # restarted at once
    after = Signer(KEY, clock)
    # Its goal may overtake its first heartbeat on the way: taken, as before.
    assert why(verifier, SEND_GOAL, b"goal2", after.sign(SEND_GOAL, b"goal2")) is None
    assert why(verifier, HEARTBEAT, b"beat", after.sign(HEARTBEAT, b"beat")) is None
    assert why(verifier, SEND_GOAL, b"goal", held_goal) == SUPERSEDED
    assert why(verifier, CMD_VEL, b"go", held_twist) == SUPERSEDED
    assert why(verifier, CMD_VEL, b"went", taken) == REPLAYED, "one taken before is still a replay"
    assert why(verifier, CMD_VEL, b"go2", after.sign(CMD_VEL, b"go2")) is None


def test_of_two_safeties_beating_at_once_the_newest_heard_is_followed_while_the_other_goes_on() -> None:
    clock = Clock()
    verifier = Verifier(KEY, clock)
    old, new = Signer(KEY, clock), Signer(KEY, clock)
    assert why(verifier, HEARTBEAT, b"old", old.sign(HEARTBEAT, b"old")) is None
    assert why(verifier, HEARTBEAT, b"new", new.sign(HEARTBEAT, b"new")) is None
    for _ in range(20):  # far longer than a silent session is remembered
        clock.now += 0.5
        assert why(verifier, HEARTBEAT, b"old", old.sign(HEARTBEAT, b"old")) == SUPERSEDED
        assert why(verifier, HEARTBEAT, b"new", new.sign(HEARTBEAT, b"new")) is None


def test_a_key_holder_that_never_beats_is_not_superseded_by_safetys_heartbeat() -> None:
    """As tests and a robot contract suite play it: commands from one session, heartbeats from another."""
    clock = Clock()
    verifier = Verifier(KEY, clock)
    safety, holder = Signer(KEY, clock), Signer(KEY, clock)
    for _ in range(3):
        clock.now += 0.02
        assert why(verifier, HEARTBEAT, b"beat", safety.sign(HEARTBEAT, b"beat")) is None
        assert why(verifier, CMD_VEL, b"go", holder.sign(CMD_VEL, b"go")) is None
