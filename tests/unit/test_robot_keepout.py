"""The robot's own keep-out check (services/robotrules.py KeepOut): goals and cmd_vel a robot refuses
before its footprint enters a zone, whoever sent them. Pure logic."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.common import Pose2D
from schemas.robot import NavigateToPoseGoal
from services.repeats import Problems
from services.robotrules import KeepOut
from services.worldmodel import load_world

WORLD = load_world()
HOLD = 0.5  # seconds a cmd_vel is held


@pytest.fixture(scope="module")
def keep_out() -> KeepOut:
    return KeepOut.of(WORLD)


def test_the_zones_are_the_worlds(keep_out: KeepOut) -> None:
    assert set(keep_out.zones) == {"stairs"}
    assert (keep_out.length, keep_out.width) == (WORLD.robot.base_size.x, WORLD.robot.base_size.y)


def test_a_goal_into_a_zone_is_refused_naming_it(keep_out: KeepOut) -> None:
    goal = NavigateToPoseGoal(pose=Pose2D(x=11.2, y=8.0, yaw=math.pi / 2))
    reason = keep_out.goal(goal, Pose2D(x=9.0, y=6.0))
    assert reason is not None and "keep-out zone 'stairs'" in reason and "(11.20, 8.00)" in reason


def test_a_goal_whose_straight_route_crosses_a_zone_is_refused_though_its_target_is_clear(keep_out: KeepOut) -> None:
    start = Pose2D(x=9.9, y=7.6, yaw=-0.6)
    goal = NavigateToPoseGoal(pose=Pose2D(x=11.5, y=6.3, yaw=-0.6), start=start)
    assert keep_out.goal(NavigateToPoseGoal(pose=goal.pose), Pose2D(x=11.5, y=5.6, yaw=math.pi / 2)) is None
    reason = keep_out.goal(goal, None)  # from the goal's own start, as safety checked it
    assert reason is not None and "'stairs'" in reason
    # The same target by a path around the zone's corner is driven.
    around = NavigateToPoseGoal(pose=goal.pose, path=[Pose2D(x=9.9, y=6.3)], start=start)
    assert keep_out.goal(around, None) is None


def test_a_goal_from_an_unknown_pose_is_refused(keep_out: KeepOut) -> None:
    assert "pose is unknown" in (keep_out.goal(NavigateToPoseGoal(pose=Pose2D(x=9.0, y=1.2)), None) or "")


@pytest.mark.parametrize(
    ("here", "linear", "angular", "enters"),
    [
        (Pose2D(x=9.8, y=8.0, yaw=0.0), 0.6, 0.0, True),  # heading for the stairs
        (Pose2D(x=9.6, y=8.0, yaw=math.pi), 0.6, 0.0, False),  # away from them
        (Pose2D(x=9.8, y=8.0, yaw=0.0), -0.6, 0.0, False),  # backing away
        (Pose2D(x=9.8, y=8.0, yaw=0.0), 0.15, 0.0, False),  # slowly: it stops in time
        (Pose2D(x=10.15, y=8.0, yaw=0.0), 0.0, 1.0, True),  # turning in place: its corners swing in
        (Pose2D(x=9.0, y=1.2, yaw=0.0), 0.6, 0.5, False),  # nowhere near
        (Pose2D(x=11.2, y=8.0, yaw=0.0), 0.6, 0.0, False),  # already in it: it may leave
    ],
)
def test_a_cmd_vel_that_would_drive_the_footprint_into_a_zone_is_refused(
    keep_out: KeepOut, here: Pose2D, linear: float, angular: float, enters: bool
) -> None:
    reason = keep_out.drive(here, linear, angular, HOLD)
    assert (reason is not None) is enters, reason
    if enters:
        assert reason is not None and "keep-out zone 'stairs'" in reason


def test_braking_counts_a_fast_cmd_vel_that_stops_just_short_without_it_is_refused(keep_out: KeepOut) -> None:
    front = 10.5 - 0.01  # where the front edge would be after the hold, without braking
    here = Pose2D(x=front - WORLD.robot.base_size.x / 2 - 0.6 * HOLD, y=8.0, yaw=0.0)
    assert keep_out.drive(here, 0.6, 0.0, HOLD) is not None
    assert KeepOut(keep_out.zones, keep_out.length, keep_out.width, (1e9, 1e9)).drive(here, 0.6, 0.0, HOLD) is None


# The stairs are x 10.5..12, y 7..9; the base 0.6 x 0.5 m: at x = 10.35 facing +x its front 0.15 m is in them.
TOUCHING_STAIRS = Pose2D(x=10.35, y=8.0, yaw=0.0)


@pytest.mark.parametrize(
    ("linear", "angular", "refused"),
    [
        (0.6, 0.0, True),  # deeper in
        (-0.6, 0.0, False),  # backing out: the overlap shrinks
        (0.6, 0.8, True),  # an arc further in
    ],
)
def test_a_base_partly_in_a_zone_may_not_drive_deeper_into_it(
    keep_out: KeepOut, linear: float, angular: float, refused: bool
) -> None:
    reason = keep_out.drive(TOUCHING_STAIRS, linear, angular, HOLD)
    assert (reason is not None) is refused, reason
    if refused:
        assert reason is not None and "keep-out zone 'stairs'" in reason


def test_a_goal_from_partly_in_a_zone_may_leave_it_but_not_go_in_or_through(keep_out: KeepOut) -> None:
    into = keep_out.goal(NavigateToPoseGoal(pose=Pose2D(x=11.2, y=8.0)), TOUCHING_STAIRS)
    assert into is not None and "'stairs'" in into
    through = keep_out.goal(NavigateToPoseGoal(pose=Pose2D(x=12.6, y=8.0)), TOUCHING_STAIRS)
    assert through is not None and "'stairs'" in through
    assert keep_out.goal(NavigateToPoseGoal(pose=Pose2D(x=9.0, y=8.0, yaw=0.0)), TOUCHING_STAIRS) is None


def test_a_stop_always_passes_and_a_drive_from_an_unknown_pose_never(keep_out: KeepOut) -> None:
    assert keep_out.drive(None, 0.0, 0.0, HOLD) is None
    assert "pose is unknown" in (keep_out.drive(None, 0.2, 0.0, HOLD) or "")


def test_problems_count_each_kind_and_log_a_flood_once(caplog: pytest.LogCaptureFixture) -> None:
    problems = Problems(wall_clock=lambda: 100.0)
    with caplog.at_level("WARNING", logger="services.repeats"):
        for _ in range(50):
            problems.note("refused a cmd_vel: into 'stairs'", "robot/cmd_vel")
    assert problems.recent(60.0) == [("refused a cmd_vel: into 'stairs' (50 so far)", 100.0)]
    assert len([r for r in caplog.records if r.name == "services.repeats"]) == 1


@settings(max_examples=300, deadline=None)
@given(
    x=st.floats(7.0, 14.0),
    y=st.floats(4.0, 10.0),
    yaw=st.floats(-math.pi, math.pi),
    linear=st.floats(-1.5, 1.5),
    angular=st.floats(-2.0, 2.0),
)
def test_skipping_zones_out_of_reach_never_changes_a_cmd_vel_verdict(
    x: float, y: float, yaw: float, linear: float, angular: float
) -> None:
    fast = KeepOut.of(WORLD)
    # The same check with every zone's box stretched over the plane: the sweep always runs.
    full = KeepOut.of(WORLD)
    full._bounds = [(-math.inf, -math.inf, math.inf, math.inf)] * len(full.zones)
    here = Pose2D(x=x, y=y, yaw=yaw)
    assert fast.drive(here, linear, angular, HOLD) == full.drive(here, linear, angular, HOLD)
