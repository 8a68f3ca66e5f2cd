"""The heartbeat guard judges a heartbeat by its stamp too, tick by tick: one a stalled link held back
counts for less, or not at all, when it finally arrives; a timely one still counts the full timeout."""

from __future__ import annotations

import math

import pytest

from schemas.safety import EstopState, SafetyStatus
from services.robotrules import HEARTBEAT_MAX_AGE, HeartbeatGuard

TIMEOUT = 0.2
MAX_AGE = 0.5
WALL = 1_700_000_000.0  # the wall clock when the monotonic one reads 0


class Clocks:
    """One host's clocks, moved together: monotonic `now`, the wall clock WALL ahead of it."""

    def __init__(self) -> None:
        self.now = 100.0

    def monotonic(self) -> float:
        return self.now

    def wall(self) -> float:
        return WALL + self.now


def beat(stamp: float, latched: bool = False) -> SafetyStatus:
    return SafetyStatus(seq=1, stamp=stamp, estop=EstopState(latched=latched, source="operator", reason="test"))


@pytest.fixture
def clocks() -> Clocks:
    return Clocks()


@pytest.fixture
def guard(clocks: Clocks) -> HeartbeatGuard:
    return HeartbeatGuard(TIMEOUT, 0.01, clocks.monotonic, max_age=MAX_AGE, wall_clock=clocks.wall)


def test_a_timely_heartbeat_counts_for_the_whole_timeout(clocks: Clocks, guard: HeartbeatGuard) -> None:
    guard.heard(beat(clocks.wall() - 0.005))
    clocks.now += TIMEOUT - 0.001
    assert guard.block() is None
    clocks.now += 0.002
    assert guard.block() == "no safety heartbeat for 201 ms"


def test_a_heartbeat_held_back_by_a_stalled_link_does_not_count_when_it_arrives(
    clocks: Clocks, guard: HeartbeatGuard
) -> None:
    guard.heard(beat(clocks.wall()))
    sent = clocks.wall() + 0.05  # safety's next beat, held a second on the way
    clocks.now += 1.05
    guard.heard(beat(sent))
    reason = guard.block()
    assert (
        reason
        == "no fresh safety heartbeat: the latest was stamped 1000 ms before it arrived (heartbeat_max_age 500 ms)"
    )
    assert guard.poll().blocked == reason


def test_a_late_heartbeat_counts_only_until_its_stamp_is_max_age_old(clocks: Clocks, guard: HeartbeatGuard) -> None:
    clocks.now += 1.0
    guard.heard(beat(clocks.wall() - 0.4))  # 400 ms on the way: counts 100 ms more, not 200
    assert guard.stale_at() == pytest.approx(clocks.now + MAX_AGE - 0.4)
    clocks.now += 0.099
    assert guard.block() is None
    clocks.now += 0.002
    assert guard.block() is not None


def test_a_late_heartbeat_does_not_cut_short_an_earlier_timely_one_and_its_latch_still_holds(
    clocks: Clocks, guard: HeartbeatGuard
) -> None:
    guard.heard(beat(clocks.wall()))
    stale_at = guard.stale_at()
    clocks.now += 0.05
    guard.heard(beat(clocks.wall() - 2.0, latched=True))  # too old to count, but its e-stop is taken
    assert guard.stale_at() == stale_at
    assert guard.block() == "e-stop latched by operator: test"


def test_a_robot_clock_behind_safetys_is_no_reason_to_stop(clocks: Clocks, guard: HeartbeatGuard) -> None:
    guard.heard(beat(clocks.wall() + 1.0))  # stamped "in the future": counts as just sent, no longer
    clocks.now += TIMEOUT - 0.001
    assert guard.block() is None
    clocks.now += 0.002
    assert guard.block() is not None


@pytest.mark.parametrize("stamp", [math.nan, math.inf, -math.inf])
def test_a_stamp_that_is_no_time_never_counts(clocks: Clocks, guard: HeartbeatGuard, stamp: float) -> None:
    guard.heard(beat(stamp))
    clocks.now += 0.001
    assert guard.block() is not None


def test_both_backends_default_to_the_guards_max_age() -> None:
    from services.ros2.config import Ros2Config
    from services.sim.config import SimConfig

    assert SimConfig().heartbeat_max_age == Ros2Config().heartbeat_max_age == HEARTBEAT_MAX_AGE
