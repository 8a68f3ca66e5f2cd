"""`tether status --check`'s heartbeat: fresh only when stamped near now and carrying a robot-link MAC."""

from __future__ import annotations

import secrets

from schemas import keys
from schemas.safety import EstopState, SafetyStatus
from services.robotlink import Signer
from services.runtime import encode
from tether.client import HeartbeatWait

NOW = 1_800_000_000.0
KEY = keys.HEARTBEAT.key("r1")


def status(stamp: float, latched: bool = False) -> SafetyStatus:
    return SafetyStatus(seq=1, stamp=stamp, estop=EstopState(latched=latched, source="operator"))


def arrive(wait: HeartbeatWait, beat: SafetyStatus, attachment: bytes | None) -> None:
    """What the subscriber does with a sample: verify before decoding, then hand over the message."""
    if wait.verify(KEY, encode(beat), attachment) is None:
        wait.take(beat)


def signed(beat: SafetyStatus) -> bytes:
    return Signer(secrets.token_bytes(32), lambda: beat.stamp).sign(KEY, encode(beat))


def test_an_old_beat_delivered_late_is_not_fresh() -> None:
    wait = HeartbeatWait(fresh=1.5, clock=lambda: NOW)
    old = status(NOW - 30.0)  # buffered across a stalled link, arriving now
    arrive(wait, old, signed(old))
    assert wait.wait(0.0) is None
    assert "stale" in wait.why_not(1.5) and "30.0 s ago" in wait.why_not(1.5)
    ahead = status(NOW + 5.0)
    arrive(wait, ahead, signed(ahead))
    assert wait.wait(0.0) is None and "ahead" in wait.why_not(1.5)
    fresh = status(NOW - 0.1)
    arrive(wait, fresh, signed(fresh))
    assert wait.wait(0.0) == fresh


def test_an_unsigned_beat_is_not_taken_and_its_latch_never_shown() -> None:
    wait = HeartbeatWait(fresh=1.5, clock=lambda: NOW)
    arrive(wait, status(NOW, latched=False), None)  # a forgery without the robot link's MAC
    arrive(wait, status(NOW, latched=False), b"not a signature")
    assert wait.wait(0.0) is None
    assert "2 without a robot-link MAC" in wait.why_not(1.5)
    beat = status(NOW, latched=True)
    arrive(wait, beat, signed(beat))
    taken = wait.wait(0.0)
    assert taken is not None and taken.estop.latched


def test_nothing_at_all_says_so() -> None:
    wait = HeartbeatWait(fresh=1.5, clock=lambda: NOW)
    assert wait.wait(0.01) is None and wait.why_not(1.5) == "no heartbeat from safety within 1.5 s"
