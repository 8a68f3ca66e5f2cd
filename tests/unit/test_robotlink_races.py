"""The robot link over time: a superseded safety that falls silent and speaks again. Pure logic."""

from __future__ import annotations

from schemas import keys
from services.robotlink import MAX_SESSIONS, MAX_SKEW, SUPERSEDED, Signer, Verifier

KEY = bytes(range(32))
ROBOT = "robot1"
CMD_VEL = keys.ROBOT_CMD_VEL.key(ROBOT)
HEARTBEAT = keys.HEARTBEAT.key(ROBOT)


class Clock:
    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def test_a_superseded_safety_silent_for_a_while_is_still_superseded_when_it_speaks_again() -> None:
    """An old safety frozen (a suspended laptop, a stopped process) while a new one took over was
    forgotten once silent for 2 x MAX_SKEW: resumed, its twists were taken again and its heartbeat
    superseded the live safety, whose commands the robot then refused."""
    clock = Clock()
    verifier = Verifier(KEY, clock)
    old, new = Signer(KEY, clock), Signer(KEY, clock)
    assert verifier.check(HEARTBEAT, b"old", old.sign(HEARTBEAT, b"old")) is None
    assert verifier.check(HEARTBEAT, b"new", new.sign(HEARTBEAT, b"new")) is None
    while clock.now < 1000.0 + 4 * MAX_SKEW:  # the old one silent, the new one beating
        clock.now += 0.5
        assert verifier.check(HEARTBEAT, b"new", new.sign(HEARTBEAT, b"new")) is None
    twist = verifier.check(CMD_VEL, b"go", old.sign(CMD_VEL, b"go"))
    assert twist is not None and twist.why == SUPERSEDED, twist
    beat = verifier.check(HEARTBEAT, b"old", old.sign(HEARTBEAT, b"old"))
    assert beat is not None and beat.why == SUPERSEDED, beat
    assert verifier.check(CMD_VEL, b"go", new.sign(CMD_VEL, b"go")) is None, "the live safety must stay heard"


def test_a_safety_frozen_before_the_next_one_started_is_superseded_by_it() -> None:
    """The old safety falls silent first (frozen), a new one starts a while later: the old one, silent
    for 2 x MAX_SKEW, was forgotten as the one beating, so the new one's heartbeat superseded nothing
    and the old one, resumed, was taken again beside it."""
    clock = Clock()
    verifier = Verifier(KEY, clock)
    old, new = Signer(KEY, clock), Signer(KEY, clock)
    assert verifier.check(HEARTBEAT, b"old", old.sign(HEARTBEAT, b"old")) is None
    clock.now += 4 * MAX_SKEW
    for _ in range(3):
        clock.now += 0.05
        assert verifier.check(HEARTBEAT, b"new", new.sign(HEARTBEAT, b"new")) is None
    twist = verifier.check(CMD_VEL, b"go", old.sign(CMD_VEL, b"go"))
    assert twist is not None and twist.why == SUPERSEDED, twist
    beat = verifier.check(HEARTBEAT, b"old", old.sign(HEARTBEAT, b"old"))
    assert beat is not None and beat.why == SUPERSEDED, beat
    assert verifier.check(CMD_VEL, b"go", new.sign(CMD_VEL, b"go")) is None, "the live safety must stay heard"


def test_a_safety_silent_for_a_while_with_no_other_beating_is_heard_again() -> None:
    """No other safety took over: the one that beat before is still the robot's safety."""
    clock = Clock()
    verifier = Verifier(KEY, clock)
    safety = Signer(KEY, clock)
    assert verifier.check(HEARTBEAT, b"beat", safety.sign(HEARTBEAT, b"beat")) is None
    clock.now += 10 * MAX_SKEW
    assert verifier.check(HEARTBEAT, b"beat", safety.sign(HEARTBEAT, b"beat")) is None
    assert verifier.check(CMD_VEL, b"go", safety.sign(CMD_VEL, b"go")) is None


def test_superseded_sessions_are_remembered_within_a_bound() -> None:
    """Each safety start is one session; what is remembered of them stays bounded."""
    clock = Clock()
    verifier = Verifier(KEY, clock)
    for _ in range(3 * MAX_SESSIONS):
        clock.now += 0.01
        signer = Signer(KEY, clock)
        assert verifier.check(HEARTBEAT, b"beat", signer.sign(HEARTBEAT, b"beat")) is None
    assert len(verifier._superseded) <= MAX_SESSIONS
    assert len(verifier._newest) <= MAX_SESSIONS
