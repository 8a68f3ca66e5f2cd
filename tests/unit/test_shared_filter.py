"""Shared control's teleop filter, driven tick by tick on a floor with one wall: it slows to a stop
before the wall, slides along it at an angle, leaves motion away alone, slows near people, and never
speeds up or lets the predicted footprint reach the wall."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Point, box

from schemas.common import Pose2D
from schemas.robot import Twist
from schemas.safety import ControlMode, Decision, ModeRequest, Rule
from services.footprint import footprint
from services.safety.gate import SafetyGate
from services.safety.latch import EstopLatch
from services.safety.modes import ModeFile
from services.safety.policy import SafetyPolicy
from services.safety.shared import STOP_DISTANCE, SharedFilter, SharedLimits, Surroundings, predict
from tests.unit.test_safety_gate import TOKEN, FakeClock, nobody, odom
from tests.unit.test_safety_gate import policy as policy  # the module-scoped fixture, shared

LENGTH, WIDTH = 0.6, 0.5
LIMITS = SharedLimits(
    horizon=1.0, braking=1.5, max_angular=1.2, length=LENGTH, width=WIDTH, radius=math.hypot(LENGTH, WIDTH) / 2
)
FILTER = SharedFilter(LIMITS)
# A wall along y = 0 (its face), the floor above it.
WALL = box(-20.0, -0.1, 20.0, 0.0)
AROUND = Surroundings(obstacles=[("the wall", WALL)])
DT = 0.05


def gap(pose: Pose2D) -> float:
    return footprint(pose.x, pose.y, pose.yaw, LENGTH, WIDTH).distance(WALL)


def step(pose: Pose2D, twist: Twist, dt: float = DT) -> Pose2D:
    """The base after holding `twist` for `dt` (exact unicycle arc)."""
    v, w = twist.linear_x, twist.angular_z
    yaw = pose.yaw + w * dt
    if abs(w) < 1e-9:
        return Pose2D(x=pose.x + v * dt * math.cos(pose.yaw), y=pose.y + v * dt * math.sin(pose.yaw), yaw=yaw)
    return Pose2D(
        x=pose.x + v / w * (math.sin(yaw) - math.sin(pose.yaw)),
        y=pose.y - v / w * (math.cos(yaw) - math.cos(pose.yaw)),
        yaw=yaw,
    )


def drive(pose: Pose2D, command: Twist, seconds: float) -> tuple[Pose2D, list[Twist]]:
    sent = []
    for _ in range(round(seconds / DT)):
        out = FILTER.filter(command, pose, AROUND).twist
        sent.append(out)
        pose = step(pose, out)
    return pose, sent


def test_straight_at_a_wall_the_speed_falls_to_zero_before_contact() -> None:
    start = Pose2D(x=0.0, y=1.5, yaw=-math.pi / 2)
    end, sent = drive(start, Twist(linear_x=0.6), 20.0)
    speeds = [t.linear_x for t in sent]
    assert speeds[0] == pytest.approx(0.6)
    assert all(b <= a + 1e-9 for a, b in itertools.pairwise(speeds)), "it sped up approaching"
    assert speeds[-1] < 0.01
    assert 0.0 < gap(end) <= STOP_DISTANCE + 0.01
    assert abs(end.x) < 1e-6 and all(abs(t.angular_z) < 1e-9 for t in sent), "straight on, nothing to steer"
    # Even told to go on at full speed once there, it does not move closer.
    at = FILTER.filter(Twist(linear_x=0.6), end, AROUND)
    assert at.twist.linear_x < 0.01 and at.slowed and "shared:" in at.note and at.values["shared"] == 1.0


def test_a_few_degrees_off_head_on_it_stops_without_turning_away() -> None:
    start = Pose2D(x=0.0, y=1.5, yaw=-math.pi / 2 + math.radians(10))
    end, sent = drive(start, Twist(linear_x=0.6), 20.0)
    assert all(t.angular_z == 0.0 for t in sent) and end.yaw == start.yaw
    assert 0.0 < gap(end) <= STOP_DISTANCE + 0.01 and sent[-1].linear_x < 0.01


def test_at_45_degrees_to_a_wall_it_slides_along_it() -> None:
    start = Pose2D(x=0.0, y=1.2, yaw=-math.pi / 4)
    end, sent = drive(start, Twist(linear_x=0.4), 12.0)
    poses = [start]
    for twist in sent:
        poses.append(step(poses[-1], twist))
    assert min(gap(p) for p in poses) > 0.0
    assert end.x > 2.0, f"it stopped dead instead of sliding along (x {end.x:.2f})"
    assert abs(math.remainder(end.yaw, math.tau)) < math.radians(10), "it did not turn along the wall"
    assert 0.0 < gap(end) <= 0.3
    # It kept moving all the way (slower while it turned), steered only towards the wall's direction.
    assert min(t.linear_x for t in sent) > 0.1 and max(t.angular_z for t in sent) > 0.1
    assert all(t.angular_z >= 0.0 for t in sent)
    first = next(FILTER.filter(Twist(linear_x=0.4), p, AROUND) for p in poses if gap(p) < 0.4)
    assert first.deflected and "slide along" in first.note and first.values["shared_steer_rps"] > 0


def test_away_from_a_wall_and_along_it_is_unchanged() -> None:
    near = Pose2D(x=0.0, y=0.25 + 0.1, yaw=math.pi / 2)  # the back 10 cm from the wall, facing away
    away = FILTER.filter(Twist(linear_x=0.5, angular_z=0.2), near, AROUND)
    assert (away.twist.linear_x, away.twist.angular_z) == (0.5, 0.2) and not away.changed and away.note == ""
    along = Pose2D(x=0.0, y=0.25 + 0.1, yaw=0.0)  # the side 10 cm from it, driving parallel
    parallel = FILTER.filter(Twist(linear_x=0.5), along, AROUND)
    assert parallel.twist.linear_x == 0.5 and not parallel.changed
    backing = Pose2D(x=0.0, y=0.3 + 0.1, yaw=-math.pi / 2)  # facing the wall, backing off it
    back = FILTER.filter(Twist(linear_x=-0.5), backing, AROUND)
    assert back.twist.linear_x == -0.5 and not back.changed


def test_near_a_person_it_is_slower_in_proportion() -> None:
    open_floor = Pose2D(x=0.0, y=5.0, yaw=0.0)
    alone = FILTER.filter(Twist(linear_x=0.3, angular_z=0.5), open_floor, AROUND)
    near = FILTER.filter(Twist(linear_x=0.3, angular_z=0.5), open_floor, AROUND, people_scale=0.4)
    assert (alone.twist.linear_x, alone.twist.angular_z) == (0.3, 0.5)
    assert near.twist.linear_x == pytest.approx(0.12) and near.twist.angular_z == pytest.approx(0.2)
    assert near.slowed and "a person is near" in near.note


def test_a_person_standing_ahead_is_kept_off_like_a_wall() -> None:
    person = Surroundings(obstacles=[("person operator", Point(2.0, 5.0).buffer(0.2))])
    pose = Pose2D(x=0.0, y=5.0, yaw=0.0)
    for _ in range(400):
        pose = step(pose, FILTER.filter(Twist(linear_x=0.5), pose, person).twist)
    assert footprint(pose.x, pose.y, pose.yaw, LENGTH, WIDTH).distance(person.obstacles[0][1]) > 0.0


def test_a_turn_in_place_is_allowed_unless_it_would_touch() -> None:
    # Parallel to the wall, its side 3 cm off: turning swings a corner into it.
    tight = Pose2D(x=0.0, y=0.25 + 0.03, yaw=0.0)
    turn = FILTER.filter(Twist(angular_z=1.0), tight, AROUND)
    assert turn.twist.angular_z == 0.0 and turn.slowed
    # 20 cm off (more than the half-diagonal sticks out), it turns freely.
    roomy = Pose2D(x=0.0, y=math.hypot(LENGTH, WIDTH) / 2 + 0.05, yaw=0.0)
    free = FILTER.filter(Twist(angular_z=1.0), roomy, AROUND)
    assert free.twist.angular_z == 1.0 and not free.changed


def test_a_footprint_already_in_the_wall_goes_no_deeper_but_may_back_off_or_slide_along() -> None:
    """Touching or overlapping, the wall was 0 away however deep: every path passed the guard, and
    the base drove on into the wall at 41% of the request (a review's finding)."""
    for depth in (0.0, 0.02, 0.04):  # how far the footprint's front is into the wall
        facing = Pose2D(x=0.0, y=LENGTH / 2 - depth, yaw=-math.pi / 2)
        for yaw_off in (0.0, math.radians(45)):
            pose = Pose2D(x=facing.x, y=facing.y, yaw=facing.yaw + yaw_off)
            into = footprint(pose.x, pose.y, pose.yaw, LENGTH, WIDTH).intersection(WALL).area
            out = FILTER.filter(Twist(linear_x=0.3), pose, AROUND).twist
            xs, ys, yaws = predict(pose, out, LIMITS)
            deepest = max(
                footprint(px, py, pyaw, LENGTH, WIDTH).intersection(WALL).area
                for px, py, pyaw in zip(xs, ys, yaws, strict=True)
            )
            assert deepest <= into + 1e-6, (depth, yaw_off, out)
            assert FILTER.guard(Twist(linear_x=0.3), pose, AROUND).twist.linear_x == 0.0
        back = FILTER.filter(Twist(linear_x=-0.3), facing, AROUND)
        assert back.twist.linear_x == -0.3, "backing off the wall is not slowed"
    # Alongside the wall, its side touching it: driving along it stays as it is.
    alongside = Pose2D(x=0.0, y=WIDTH / 2, yaw=0.0)
    assert FILTER.guard(Twist(linear_x=0.3), alongside, AROUND).twist.linear_x == pytest.approx(0.3)


def test_a_keep_out_zone_is_kept_off_by_the_bases_disc() -> None:
    zone = Surroundings(zones=[("keep-out zone 'stairs'", box(3.0, 4.0, 5.0, 6.0))])
    pose = Pose2D(x=0.0, y=5.0, yaw=0.0)
    for _ in range(400):
        pose = step(pose, FILTER.filter(Twist(linear_x=0.5), pose, zone).twist)
    assert Point(pose.x, pose.y).distance(zone.zones[0][1]) > LIMITS.radius
    assert pose.x > 3.0 - LIMITS.radius - 0.1, "it stopped far short"


@settings(max_examples=300, deadline=None)
@given(
    x=st.floats(-1.0, 1.0),
    y=st.floats(0.42, 2.0),
    yaw=st.floats(-math.pi, math.pi),
    v=st.floats(-0.6, 0.6),
    w=st.floats(-1.2, 1.2),
    people=st.sampled_from([1.0, 0.4]),
)
def test_never_faster_and_the_predicted_footprint_never_reaches_the_wall(
    x: float, y: float, yaw: float, v: float, w: float, people: float
) -> None:
    pose = Pose2D(x=x, y=y, yaw=yaw)
    if gap(pose) < 0.02:
        return  # the property is about a base that stands clear
    out = FILTER.filter(Twist(linear_x=v, angular_z=w), pose, AROUND, people_scale=people).twist
    assert abs(out.linear_x) <= abs(v) + 1e-12
    assert out.linear_x * v >= 0.0, "the filter reversed the command"
    assert abs(out.angular_z) <= LIMITS.max_angular + 1e-12
    xs, ys, yaws = predict(pose, out, LIMITS)
    for px, py, pyaw in zip(xs, ys, yaws, strict=True):
        assert footprint(px, py, pyaw, LENGTH, WIDTH).distance(WALL) > 0.0


def test_the_gate_filters_teleop_only_in_shared_mode_and_its_event_says_so(
    policy: SafetyPolicy, tmp_path: Path
) -> None:
    # Facing the south wall of the living room, the base's front 10 cm from it.
    close = Pose2D(x=6.0, y=0.05 + 0.3 + 0.1, yaw=-math.pi / 2)
    rulings = {}
    for mode in (ControlMode.DIRECT, ControlMode.SHARED):
        clock = FakeClock()
        gate = SafetyGate(policy, EstopLatch(TOKEN), clock, FakeClock(), modes=ModeFile(tmp_path / f"{mode}.json"))
        gate.odometry(odom(pose=close))
        nobody(gate)
        assert gate.set_mode(ModeRequest(operator="alice", token=TOKEN, mode=mode)).forward.ok
        for _ in range(10):  # past the acceleration ramp
            clock.advance(0.05)
            gate.odometry(odom(pose=close))
            rulings[mode] = gate.teleop(Twist(linear_x=0.3))
    direct, shared = rulings[ControlMode.DIRECT], rulings[ControlMode.SHARED]
    assert direct.forward is not None and direct.forward.linear_x == pytest.approx(0.3)
    assert "shared" not in direct.events[0].values
    assert shared.forward is not None and 0.0 <= shared.forward.linear_x < 0.1
    (event,) = shared.events
    assert event.decision is Decision.CLAMPED and event.rule is Rule.OBSTACLE
    assert event.values["shared"] == 1.0 and event.values["requested_mps"] == 0.3
    assert "shared:" in event.reason and "the outer wall" in event.reason, event.reason
