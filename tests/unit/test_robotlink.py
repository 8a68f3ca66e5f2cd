"""The robot link's MAC, replay window and key file, and coalescing repeated complaints: pure logic."""

from __future__ import annotations

import multiprocessing
import os
import secrets
import stat
import struct
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import hashes as crypto_hashes
from cryptography.hazmat.primitives import hmac as crypto_hmac

from schemas import keys
from services.repeats import MAX_KEYS, RepeatLog
from services.robotlink import (
    BAD_MAC,
    BEFORE_START,
    MALFORMED,
    MAX_SKEW,
    NOT_SIGNED,
    REPLAYED,
    STALE,
    KeyFileError,
    LinkGuard,
    Signer,
    Verifier,
    ensure_key,
    key_path,
    read_key,
    signed,
)

KEY = bytes(range(32))
CMD_VEL = keys.ROBOT_CMD_VEL.key("robot1")
HEARTBEAT = keys.HEARTBEAT.key("robot1")
SEND_GOAL = keys.ROBOT_NAVIGATE.send_goal.key("robot1")


class Clock:
    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def pair(clock: Clock | None = None) -> tuple[Signer, Verifier, Clock]:
    clock = clock or Clock()
    return Signer(KEY, clock), Verifier(KEY, clock), clock


def test_safetys_commands_and_heartbeat_are_signed_and_nothing_else() -> None:
    assert signed(CMD_VEL) and signed(HEARTBEAT) and signed(SEND_GOAL)
    assert signed(keys.ROBOT_GRIPPER.cancel_goal.key("r"))
    assert not signed(keys.ODOM.key("robot1"))
    assert not signed(keys.ROBOT_NAVIGATE.get_result.key("robot1"))
    assert not signed(keys.CMD_VEL.key("robot1")), "cmd/cmd_vel goes to safety, not the robot"


def test_the_attachment_and_its_mac_are_laid_out_as_a_robot_of_another_make_would_compute_them() -> None:
    # Spelled out here, and the MAC computed by another HMAC (cryptography's OpenSSL binding): signer and
    # verifier share one function, so a change to what it covers would pass every other test here.
    session, payload = bytes(range(100, 116)), b'{"linear_x":0.2,"angular_z":0.0}'
    signer = Signer(KEY, Clock(1234.5), session=session)
    signer.sign(CMD_VEL, b"{}")
    attachment = signer.sign(CMD_VEL, payload)
    assert len(attachment) == 2 + 16 + 8 + 8 + 32
    magic, sent_session, counter, stamp, mac = struct.unpack("!2s16sQd32s", attachment)
    assert (magic, sent_session, counter, stamp) == (b"T1", session, 2, 1234.5)
    expr = CMD_VEL.encode()
    covered = (
        b"tether robot link v1\0"
        + len(expr).to_bytes(4, "big")
        + expr
        + session
        + counter.to_bytes(8, "big")
        + struct.pack("!d", stamp)
        + payload
    )
    independent = crypto_hmac.HMAC(KEY, crypto_hashes.SHA256())
    independent.update(covered)
    assert mac == independent.finalize()


def test_a_signed_message_is_taken_once() -> None:
    signer, verifier, _ = pair()
    attachment = signer.sign(CMD_VEL, b'{"linear_x":0.2}')
    assert verifier.check(CMD_VEL, b'{"linear_x":0.2}', attachment) is None
    replayed = verifier.check(CMD_VEL, b'{"linear_x":0.2}', attachment)
    assert replayed is not None and replayed.why == REPLAYED


@pytest.mark.parametrize(
    ("key_expr", "payload", "why"),
    [
        (CMD_VEL, b'{"linear_x":2.0}', BAD_MAC),  # another payload
        (keys.ROBOT_CMD_VEL.key("robot2"), b'{"linear_x":0.2}', BAD_MAC),  # another robot's key
        (HEARTBEAT, b'{"linear_x":0.2}', BAD_MAC),  # another key expression
    ],
)
def test_a_mac_covers_the_key_and_the_payload(key_expr: str, payload: bytes, why: str) -> None:
    signer, verifier, _ = pair()
    attachment = signer.sign(CMD_VEL, b'{"linear_x":0.2}')
    refusal = verifier.check(key_expr, payload, attachment)
    assert refusal is not None and refusal.why == why


def test_no_attachment_a_malformed_one_or_another_key_is_refused() -> None:
    _, verifier, clock = pair()
    assert (r := verifier.check(CMD_VEL, b"{}", None)) is not None and r.why == NOT_SIGNED
    assert (r := verifier.check(CMD_VEL, b"{}", b"x" * 10)) is not None and r.why == MALFORMED
    forged = Signer(secrets.token_bytes(32), clock).sign(CMD_VEL, b"{}")
    assert (r := verifier.check(CMD_VEL, b"{}", forged)) is not None and r.why == BAD_MAC
    flipped = bytearray(Signer(KEY, clock).sign(CMD_VEL, b"{}"))
    flipped[20] ^= 1  # the counter
    assert (r := verifier.check(CMD_VEL, b"{}", bytes(flipped))) is not None and r.why == BAD_MAC


def test_counters_must_increase_per_key_so_a_reordered_command_is_refused() -> None:
    signer, verifier, _ = pair()
    first = signer.sign(CMD_VEL, b"go")
    beat = signer.sign(HEARTBEAT, b"beat")
    stop = signer.sign(CMD_VEL, b"stop")
    assert verifier.check(CMD_VEL, b"stop", stop) is None
    late = verifier.check(CMD_VEL, b"go", first)
    assert late is not None and late.why == REPLAYED, "an older command after a newer one on the same key"
    assert verifier.check(HEARTBEAT, b"beat", beat) is None, "keys are ordered each on its own"


def test_stamps_outside_the_window_are_refused_either_way() -> None:
    signer, verifier, clock = pair()
    old = signer.sign(CMD_VEL, b"a")
    clock.now += MAX_SKEW + 0.01
    assert (r := verifier.check(CMD_VEL, b"a", old)) is not None and r.why == STALE
    ahead = Signer(KEY, Clock(clock.now + MAX_SKEW + 0.5)).sign(CMD_VEL, b"b")
    assert (r := verifier.check(CMD_VEL, b"b", ahead)) is not None and r.why == STALE
    within = Signer(KEY, Clock(clock.now + MAX_SKEW - 0.5)).sign(CMD_VEL, b"c")
    assert verifier.check(CMD_VEL, b"c", within) is None


def test_a_restarted_robot_takes_nothing_sent_before_it_started() -> None:
    clock = Clock()
    signer = Signer(KEY, clock)
    captured = signer.sign(HEARTBEAT, b"unlatched")
    clock.now += 0.5
    restarted = Verifier(KEY, clock)
    assert (r := restarted.check(HEARTBEAT, b"unlatched", captured)) is not None and r.why == BEFORE_START
    assert restarted.check(HEARTBEAT, b"latched", signer.sign(HEARTBEAT, b"latched")) is None


def test_a_restarted_safety_is_a_new_session_and_the_old_ones_messages_stay_refused() -> None:
    clock = Clock()
    verifier = Verifier(KEY, clock)
    before = Signer(KEY, clock)
    for _ in range(5):
        sent = before.sign(HEARTBEAT, b"unlatched")
        assert verifier.check(HEARTBEAT, b"unlatched", sent) is None
    clock.now += 0.1
    after = Signer(KEY, clock)  # safety restarted: its counter starts at 1 again
    assert after.session != before.session
    assert verifier.check(HEARTBEAT, b"latched", after.sign(HEARTBEAT, b"latched")) is None
    # A replay of the old session within the window: its counter was seen.
    assert (r := verifier.check(HEARTBEAT, b"unlatched", sent)) is not None and r.why == REPLAYED
    # Long after, the old session is forgotten; its messages are stale by then.
    clock.now += 3 * MAX_SKEW
    assert verifier.check(HEARTBEAT, b"latched", after.sign(HEARTBEAT, b"latched")) is None
    assert (r := verifier.check(HEARTBEAT, b"unlatched", sent)) is not None and r.why == STALE


def test_the_key_file_is_made_once_mode_0600_and_read_back(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "robot-r1.key"
    key = ensure_key(path)
    assert len(key) == 32 and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert ensure_key(path) == key == read_key(path)
    assert list(path.parent.iterdir()) == [path], "no temporary file left behind"


def _make(path: str) -> str:
    return ensure_key(Path(path)).hex()


def test_safety_and_the_robot_racing_to_make_the_key_get_the_same_one(tmp_path: Path) -> None:
    path = tmp_path / "robot-r1.key"
    with multiprocessing.get_context("spawn").Pool(8) as pool:
        made = pool.map(_make, [str(path)] * 16)
    assert len(set(made)) == 1 and bytes.fromhex(made[0]) == read_key(path)


@pytest.mark.parametrize(
    ("content", "mode", "complaint"),
    [
        ("ab" * 32, 0o644, "readable by others"),
        ("zz" * 32, 0o600, "not hex"),
        ("ab" * 16, 0o600, "holds 16 bytes"),
    ],
)
def test_a_bad_key_file_is_refused_saying_why(tmp_path: Path, content: str, mode: int, complaint: str) -> None:
    path = tmp_path / "robot.key"
    path.write_text(content)
    os.chmod(path, mode)
    with pytest.raises(KeyFileError, match=complaint):
        read_key(path)


def test_the_key_file_is_the_configs_then_the_environments_then_beside_the_token(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("TETHER_ROBOT_KEY_FILE", raising=False)
    assert key_path(None, tmp_path, "r1") == tmp_path / "robot-r1.key"
    monkeypatch.setenv("TETHER_ROBOT_KEY_FILE", str(tmp_path / "env.key"))
    assert key_path(None, tmp_path, "r1") == tmp_path / "env.key"
    assert key_path(str(tmp_path / "conf.key"), tmp_path, "r1") == tmp_path / "conf.key"


def test_a_link_guard_logs_a_flood_once_then_counts_it(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    reported: list[str] = []
    guard = LinkGuard(Verifier(KEY, clock), reported.append, wall_clock=clock, clock=clock)
    with caplog.at_level("WARNING", logger="services.robotlink"):
        for _ in range(1000):
            assert guard(CMD_VEL, b"{}", None) is not None
            clock.now += 0.001  # a 1 kHz flood for one second
        clock.now += 5.0
        assert guard(CMD_VEL, b"{}", None) is not None
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2, lines
    assert lines[0].startswith("messages refused as not from safety on robot/cmd_vel: not signed")
    assert lines[1].startswith("1000 more messages refused as not from safety on robot/cmd_vel")
    [(text, _)] = guard.problems(60.0)
    assert text == f"refused robot/cmd_vel: {NOT_SIGNED} (1001 so far)"
    assert len(reported) == 1001 and set(reported) == {f"refused robot/cmd_vel: {NOT_SIGNED}"}


def test_a_repeat_log_keeps_keys_apart() -> None:
    clock = Clock()
    repeats = RepeatLog("undecodable", period=5.0, clock=clock)
    assert repeats.note("a", "bad") == "undecodable on a: bad"
    assert repeats.note("b", "bad") == "undecodable on b: bad"
    assert repeats.note("a", "bad") is None
    assert repeats.count("a") == 1 and repeats.total == 3


def test_a_repeat_log_keeps_a_bounded_number_of_keys() -> None:
    """Its keys may be a peer's: garbage on ever new keys under a wildcard grew it without end."""
    repeats = RepeatLog("undecodable", clock=lambda: 0.0)
    for i in range(MAX_KEYS * 5):
        assert repeats.note(f"tether/r1/_trace/x{i}", "garbage") is not None  # each first one is logged
    assert len(repeats._windows) == MAX_KEYS and len(repeats._covered) == MAX_KEYS
    assert repeats.total == MAX_KEYS * 5
    # A key still kept is counted within its window as before.
    assert repeats.note(f"tether/r1/_trace/x{MAX_KEYS * 5 - 1}", "again") is None
