"""Safety's gate on a fake clock, tick by tick: the watchdog, the teleop ramp, repeated vetoes, the
speed allowed near people, the latch; no network."""

from __future__ import annotations

import pytest

from schemas import keys
from schemas.actions import GoalResponse, SendGoal
from schemas.common import Pose2D
from schemas.robot import ARM_JOINTS, JointState, NavigateToPoseGoal, Odometry, Twist
from schemas.safety import Decision, EStop, EstopSource, ResetRequest, Rule
from schemas.world import PerceivedHuman, PerceivedHumans
from services.robotmodel import ArmModel
from services.safety.gate import (
    CLOCK_STEP_BACK,
    REPEAT_WINDOW,
    TELEOP_MAX_STEP,
    TELEOP_TIMEOUT,
    Ruling,
    SafetyGate,
)
from services.safety.latch import EstopLatch
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel, load_world

WORLD = load_world()
HERE = Pose2D(x=6.0, y=1.2)
TICK = 0.02  # the heartbeat's period at 50 Hz
TOKEN = "operator-token"


@pytest.fixture(scope="module")
def policy() -> SafetyPolicy:
    arm = ArmModel(WORLD.robot.arm_urdf)
    return SafetyPolicy(WorldModel(WORLD), load_policy(None, WORLD.robot, arm, WORLD.keep_out), arm)


@pytest.fixture
def gate(policy: SafetyPolicy) -> SafetyGate:
    return SafetyGate(policy, EstopLatch(TOKEN))


def odom(linear: float = 0.0, angular: float = 0.0, pose: Pose2D = HERE) -> Odometry:
    return Odometry(stamp=0.0, sim_time=0.0, pose=pose, linear_x=linear, angular_z=angular)


def joints(velocity: float) -> JointState:
    n = len(ARM_JOINTS)
    return JointState(stamp=0.0, name=list(ARM_JOINTS), position=list(WORLD.robot.home_joints), velocity=[velocity] * n)


def nobody(gate: SafetyGate, now: float) -> None:
    """People reported, none near: full speed from the next tick."""
    gate.humans(PerceivedHumans(stamp=0.0, humans=[]), now)
    gate.tick(now)


def latched_by(ruling: Ruling[None]) -> str | None:
    return ruling.events[0].reason if ruling.latched else None


# The watchdog


def test_the_watchdog_waits_exactly_state_max_age_and_trips_one_tick_later(gate: SafetyGate) -> None:
    max_age = gate.policy.policy.monitor.state_max_age
    gate.odometry(odom(linear=0.2), 100.0)
    at_the_limit = gate.tick(100.0 + max_age)
    assert not at_the_limit.latched and not gate.latch.state.latched
    assert gate.pose(100.0 + max_age) == HERE, "a state exactly state_max_age old still counts"
    after = gate.tick(100.0 + max_age + TICK)
    assert after.latched and gate.latch.state.source == EstopSource.WATCHDOG
    (event,) = after.events
    assert (event.decision, event.rule) == (Decision.LATCHED, Rule.WATCHDOG)
    assert "no odometry for 0.52 s while the base was moving" in event.reason
    assert event.values["age_s"] == pytest.approx(max_age + TICK) and event.values["speed_mps"] == 0.2
    assert gate.pose(100.0 + max_age + TICK) is None


def test_the_watchdog_leaves_a_still_robot_alone_however_long_it_is_silent(gate: SafetyGate) -> None:
    gate.odometry(odom(), 0.0)
    gate.joint_state(joints(0.0), 0.0)
    assert not gate.tick(3600.0).latched
    assert gate.pose(3600.0) is None and gate.joint_positions(3600.0) is None


def test_the_watchdog_trips_on_an_arm_that_stops_reporting_while_moving(gate: SafetyGate) -> None:
    max_age = gate.policy.policy.monitor.state_max_age
    gate.joint_state(joints(0.5), 0.0)
    assert not gate.tick(max_age).latched
    after = gate.tick(max_age + TICK)
    assert after.latched and "no joint states for 0.52 s while the arm was moving" in after.events[0].reason
    assert after.events[0].values["speed_rps"] == 0.5


def test_a_clock_that_jumps_forwards_trips_the_watchdog_at_the_next_tick(gate: SafetyGate) -> None:
    gate.odometry(odom(linear=0.2), 0.0)
    assert not gate.tick(TICK).latched
    jumped = gate.tick(10.0)
    assert jumped.latched and jumped.events[0].values["age_s"] == pytest.approx(10.0)


def test_a_clock_that_jumps_back_neither_trips_nor_blinds_the_watchdog(gate: SafetyGate) -> None:
    max_age = gate.policy.policy.monitor.state_max_age
    gate.odometry(odom(linear=0.2), 100.0)
    # Back by a minute: no time has passed for the gate, so the state is as fresh as it was.
    assert not gate.tick(40.0).latched
    assert gate.pose(40.0) == HERE
    # From there the clock runs on: the silence is measured from the jump, not from where the clock
    # was before it, and trips after state_max_age as always.
    assert not gate.tick(40.0 + max_age).latched
    after = gate.tick(40.0 + max_age + TICK)
    assert after.latched and after.events[0].values["age_s"] == pytest.approx(max_age + TICK)


def test_after_a_clock_jump_back_the_gate_runs_on_from_where_it_was(gate: SafetyGate) -> None:
    far = PerceivedHuman(id="operator", name="operator", pose=Pose2D(x=HERE.x, y=HERE.y + 4.0))
    gate.humans(PerceivedHumans(stamp=0.0, humans=[far]), 100.0)
    gate.odometry(odom(linear=0.2), 100.0)
    gate.tick(100.0)
    now = 40.0
    for _ in range(10):  # every input and tick in step with the jumped clock
        gate.humans(PerceivedHumans(stamp=0.0, humans=[far]), now)
        gate.odometry(odom(linear=0.2), now)
        assert not gate.tick(now).latched
        assert gate.pose(now) == HERE
        now += TICK
    assert gate.separation.scale == 1.0


def test_readings_a_moment_out_of_order_count_as_the_same_instant(gate: SafetyGate) -> None:
    max_age = gate.policy.policy.monitor.state_max_age
    gate.odometry(odom(linear=0.2), 100.0)
    gate.tick(100.0 - CLOCK_STEP_BACK / 2)  # a thread that read the clock a little earlier
    assert not gate.tick(100.0 + max_age).latched
    assert gate.tick(100.0 + max_age + TICK).latched


def test_a_moving_robot_that_keeps_reporting_never_trips_the_watchdog(gate: SafetyGate) -> None:
    now = 0.0
    for _ in range(200):
        gate.odometry(odom(linear=0.2), now)
        assert not gate.tick(now + TICK / 2).latched
        now += TICK


# The teleop ramp


@pytest.fixture
def teleop_gate(gate: SafetyGate) -> SafetyGate:
    nobody(gate, 0.0)
    assert gate.separation.scale == 1.0
    return gate


def turn(gate: SafetyGate, wanted: float, now: float) -> float:
    """Ask teleop to turn in place (safe anywhere) at `wanted`; the rate sent to the robot."""
    gate.odometry(odom(), now)
    ruling = gate.teleop(Twist(angular_z=wanted), now)
    assert ruling.forward is not None, ruling.events
    return ruling.forward.angular_z


def test_teleop_speeds_up_from_a_stop_by_at_most_a_step_of_acceleration(teleop_gate: SafetyGate) -> None:
    accel = teleop_gate.policy.policy.base.max_angular_acceleration
    first = teleop_gate.teleop(Twist(angular_z=1.0), 1.0)
    assert first.forward == Twist(angular_z=pytest.approx(accel * TELEOP_MAX_STEP))
    (event,) = first.events
    assert (event.decision, event.rule) == (Decision.CLAMPED, Rule.BASE_ACCELERATION)
    assert event.values["requested_rps"] == 1.0
    # The next message speeds up from what was sent, by the time since.
    assert turn(teleop_gate, 1.0, 1.05) == pytest.approx(accel * (TELEOP_MAX_STEP + 0.05))


def test_teleop_ramps_on_exactly_at_the_timeout_and_from_a_stop_one_tick_after(teleop_gate: SafetyGate) -> None:
    accel = teleop_gate.policy.policy.base.max_angular_acceleration
    sent = turn(teleop_gate, 1.0, 1.0)
    # Silent exactly TELEOP_TIMEOUT: the robot still holds the last one; the step is capped.
    held = turn(teleop_gate, 1.0, 1.0 + TELEOP_TIMEOUT)
    assert held == pytest.approx(sent + accel * TELEOP_MAX_STEP)
    # Silent one tick longer: the base has stopped, so the ramp starts from a stop again.
    stopped = turn(teleop_gate, 1.0, 1.0 + 2 * TELEOP_TIMEOUT + TICK)
    assert stopped == pytest.approx(accel * TELEOP_MAX_STEP)


def test_teleop_after_a_clock_jump_forwards_starts_from_a_stop(teleop_gate: SafetyGate) -> None:
    accel = teleop_gate.policy.policy.base.max_angular_acceleration
    turn(teleop_gate, 1.0, 1.0)
    turn(teleop_gate, 1.0, 1.05)
    teleop_gate.humans(PerceivedHumans(stamp=0.0, humans=[]), 500.0)
    teleop_gate.tick(500.0)
    assert turn(teleop_gate, 1.0, 500.0) == pytest.approx(accel * TELEOP_MAX_STEP)


def test_teleop_after_a_clock_jump_back_does_not_speed_up(teleop_gate: SafetyGate) -> None:
    sent = turn(teleop_gate, 1.0, 100.0)
    # No time has passed for the gate: no speed-up, and no negative step either.
    assert turn(teleop_gate, 1.0, 50.0) == pytest.approx(sent)
    assert turn(teleop_gate, 0.1, 50.0) == pytest.approx(0.1), "slowing down is never limited"


def test_slowing_down_is_never_ramped(teleop_gate: SafetyGate) -> None:
    now = 1.0
    while turn(teleop_gate, 1.2, now) < 1.2 - 1e-9:
        now += 0.05
    assert turn(teleop_gate, 0.0, now + 0.01) == 0.0


def test_a_stop_sent_on_any_path_is_where_teleop_ramps_from(teleop_gate: SafetyGate) -> None:
    accel = teleop_gate.policy.policy.base.max_angular_acceleration
    now = 1.0
    while turn(teleop_gate, 1.0, now) < 1.0 - 1e-9:
        now += 0.05
    # A program's command over the limit is refused and the base stopped.
    refused = teleop_gate.cmd_vel(Twist(angular_z=3.0), now + 0.01)
    assert refused.forward == Twist() and refused.events[0].decision is Decision.VETOED
    assert turn(teleop_gate, 1.0, now + 0.02) == pytest.approx(accel * 0.01)


# Repeated vetoes


def test_vetoes_repeated_within_a_second_are_one_event_and_then_a_count(gate: SafetyGate) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"), 0.0)
    first = gate.cmd_vel(Twist(angular_z=0.1), 0.0)
    assert first.forward is None, "nothing is sent while the e-stop is latched"
    (event,) = first.events
    assert event.rule is Rule.ESTOP and "an operator must reset it" in event.reason
    for i in range(1, 50):
        assert gate.cmd_vel(Twist(angular_z=0.1), i * TICK / 2).events == ()
    assert gate.tick(REPEAT_WINDOW - 1e-6).events == (), "the count waits for the window to end"
    (count,) = gate.tick(REPEAT_WINDOW).events
    assert (count.decision, count.rule, count.values) == (Decision.VETOED, Rule.ESTOP, {"count": 49.0})
    assert count.reason.startswith("49 more vetoed like this in the last 1.0 s: e-stop latched by operator")
    assert gate.tick(REPEAT_WINDOW + TICK).events == ()
    # The next refusal starts a new window, with its own event.
    assert len(gate.cmd_vel(Twist(angular_z=0.1), REPEAT_WINDOW + 2 * TICK).events) == 1


def test_a_window_no_tick_closed_is_counted_before_the_next_veto(gate: SafetyGate) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"), 0.0)
    gate.cmd_vel(Twist(), 0.0)
    gate.cmd_vel(Twist(), 0.5)
    count, veto = gate.cmd_vel(Twist(), REPEAT_WINDOW + 0.01).events
    assert count.values == {"count": 1.0} and "count" not in veto.values
    assert gate.tick(REPEAT_WINDOW + 0.02).events == ()


def test_a_lone_veto_is_not_followed_by_a_count(gate: SafetyGate) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"), 0.0)
    gate.cmd_vel(Twist(), 0.0)
    assert gate.tick(REPEAT_WINDOW + TICK).events == ()


def test_each_stream_and_rule_is_grouped_on_its_own(gate: SafetyGate) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"), 0.0)
    for now in (0.0, 0.1, 0.2):
        gate.cmd_vel(Twist(), now)
        gate.teleop(Twist(), now)
    counts = {e.key: e.values["count"] for e in gate.tick(REPEAT_WINDOW).events}
    assert counts == {keys.CMD_VEL.path: 2.0, keys.TELEOP_CMD_VEL.path: 2.0}


def test_over_the_rate_the_base_is_stopped_and_the_refusals_grouped(gate: SafetyGate) -> None:
    nobody(gate, 0.0)
    gate.odometry(odom(), 0.0)
    rate = gate.policy.policy.rate
    burst = int(rate.max_cmd_vel_per_second * rate.burst_seconds)
    for _ in range(burst):
        assert gate.cmd_vel(Twist(angular_z=0.1), 0.0).forward == Twist(angular_z=0.1)
    over = gate.cmd_vel(Twist(angular_z=0.1), 0.0)
    assert over.forward == Twist(), "over the rate, the base is stopped"
    assert over.events[0].rule is Rule.COMMAND_RATE
    assert all(gate.cmd_vel(Twist(angular_z=0.1), 0.0).events == () for _ in range(9))
    (count,) = gate.tick(REPEAT_WINDOW).events
    assert count.rule is Rule.COMMAND_RATE and count.values == {"count": 9.0}


# The speed allowed near people


def test_the_speed_goes_down_at_once_and_back_up_with_the_release_margin(gate: SafetyGate) -> None:
    humans = gate.policy.policy.humans
    front = WORLD.robot.base_size.x / 2

    def stand(gap: float, now: float) -> Ruling[None]:
        gate.odometry(odom(), now)
        body = HERE.x + front + humans.person_radius + gap
        person = PerceivedHuman(id="operator", name="operator", pose=Pose2D(x=body, y=HERE.y))
        gate.humans(PerceivedHumans(stamp=0.0, humans=[person]), now)
        # Earlier reports still count for unseen_after: tick once they are all of this one.
        return gate.tick(now)

    nobody(gate, 0.0)
    slowed = stand(humans.slow_distance - 0.05, 0.1)
    (event,) = slowed.events
    assert (event.decision, event.rule, event.key) == (Decision.LIMITED, Rule.HUMAN_SEPARATION, keys.HEARTBEAT.path)
    assert event.values == {
        "scale": humans.reduced_speed_scale,
        "distance_m": pytest.approx(humans.slow_distance - 0.05),
    }
    now = 0.1 + humans.unseen_after + TICK
    assert stand(humans.slow_distance + humans.release_margin / 2, now).events == (), "the speed went up too soon"
    now += humans.unseen_after + TICK
    assert stand(humans.slow_distance + humans.release_margin + 0.05, now).events[0].values["scale"] == 1.0
    status = gate.status(seq=7, stamp=123.0)
    assert (status.seq, status.stamp, status.speed_scale) == (7, 123.0, 1.0)
    assert status.max_linear_speed == gate.policy.max_linear


def test_without_a_report_of_people_for_unseen_after_the_speed_is_reduced(gate: SafetyGate) -> None:
    unseen = gate.policy.policy.humans.unseen_after
    nobody(gate, 0.0)
    assert gate.tick(unseen).events == (), "a report exactly unseen_after old still counts"
    (event,) = gate.tick(unseen + TICK).events
    assert event.values["scale"] == gate.policy.policy.humans.reduced_speed_scale
    assert "no recent report" in event.reason


def test_a_separation_that_cannot_be_computed_pauses_the_robot(
    gate: SafetyGate, monkeypatch: pytest.MonkeyPatch
) -> None:
    nobody(gate, 0.0)

    def broken(now: float) -> None:
        raise RuntimeError("geometry went wrong")

    monkeypatch.setattr(gate, "_find_separation", broken)
    (event,) = gate.tick(TICK).events
    assert event.values["scale"] == 0.0 and "could not be computed: geometry went wrong" in event.reason
    assert gate.status(1, 0.0).max_linear_speed == 0.0


# The monitors, the latch, goals


def test_a_base_measured_over_the_limit_trip_after_times_latches_once(gate: SafetyGate) -> None:
    nobody(gate, 0.0)
    trip_after = gate.policy.policy.monitor.trip_after
    rulings = [gate.odometry(odom(linear=1.0), 0.1 + i * TICK) for i in range(trip_after + 2)]
    assert [r.latched for r in rulings] == [False] * (trip_after - 1) + [True, False, False]
    latched = rulings[trip_after - 1]
    assert latched.events[0].rule is Rule.MONITOR_SPEED and latched.events[0].values["speed_mps"] == 1.0
    assert gate.latch.state.source == EstopSource.MONITOR


def test_the_latch_rules_once_and_only_the_operator_token_clears_it(gate: SafetyGate) -> None:
    pressed = gate.estop(EStop(source=EstopSource.AGENT, reason="stop"), 0.0)
    assert pressed.latched and latched_by(pressed) == "by agent: stop"
    assert gate.estop(EStop(source=EstopSource.OPERATOR, reason="again"), 0.1) == Ruling(None)
    wrong = gate.reset(ResetRequest(operator="mallory", token="guess"))
    assert not wrong.reset and not wrong.forward.ok and gate.latch.state.latched
    assert wrong.events[0].command == ResetRequest(operator="mallory", token="***")
    right = gate.reset(ResetRequest(operator="alice", token=TOKEN))
    assert right.reset and right.forward.ok and not gate.latch.state.latched
    assert right.events[0].decision is Decision.RESET and TOKEN not in repr(right.events)


def test_an_estop_that_cannot_be_read_latches(gate: SafetyGate) -> None:
    ruling = gate.unreadable_estop(12, "truncated", 0.0)
    assert ruling.latched and gate.latch.state.source == "unknown"
    assert "could not be read (12 bytes): truncated" in ruling.events[0].reason


def test_a_latch_stops_the_base_and_teleop_ramps_from_that_stop(gate: SafetyGate) -> None:
    nobody(gate, 0.0)
    accel = gate.policy.policy.base.max_angular_acceleration
    now = 0.1
    while turn(gate, 1.0, now) < 1.0 - 1e-9:
        now += 0.05
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"), now + 0.01)
    gate.reset(ResetRequest(operator="alice", token=TOKEN))
    assert turn(gate, 1.0, now + 0.02) == pytest.approx(accel * 0.01)


def test_a_goal_while_latched_is_refused_as_an_estop(gate: SafetyGate) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"), 0.0)
    ruling = gate.navigate(SendGoal(goal_id="g1", goal=NavigateToPoseGoal(pose=HERE)), 0.0)
    assert isinstance(ruling.forward, GoalResponse) and not ruling.forward.accepted
    assert ruling.forward.kind is not None and ruling.forward.kind.value == "estop"
    assert ruling.forward.reason.startswith("vetoed by safety: e-stop latched by operator")


def test_an_approved_goal_is_forwarded_as_checked(gate: SafetyGate) -> None:
    gate.odometry(odom(), 0.0)
    ruling = gate.navigate(SendGoal(goal_id="g1", goal=NavigateToPoseGoal(pose=Pose2D(x=6.5, y=1.2))), 0.0)
    assert isinstance(ruling.forward, SendGoal) and ruling.forward.goal_id == "g1"
    assert ruling.forward.goal.start == HERE, "the route was checked from here"
    assert ruling.events[0].decision is Decision.APPROVED
    assert ruling.forward.goal.max_speed == gate.policy.max_linear, "no speed given: the limit filled in"
