"""Safety's gate on a fake clock, tick by tick: the watchdog, the teleop ramp, repeated vetoes, the
speed allowed near people, the latch; no network."""

from __future__ import annotations

import threading

import pytest

from schemas import keys
from schemas.actions import GoalResponse, SendGoal
from schemas.common import Pose2D
from schemas.robot import (
    ARM_JOINTS,
    FollowJointTrajectoryGoal,
    JointState,
    NavigateToPoseGoal,
    Odometry,
    TrajectoryPoint,
    Twist,
)
from schemas.safety import Decision, EStop, EstopSource, ResetRequest, Rule
from schemas.world import PerceivedHuman, PerceivedHumans
from services.robotmodel import ArmModel
from services.safety.gate import (
    REPEAT_WINDOW,
    TELEOP_MAX_STEP,
    TELEOP_TIMEOUT,
    Ruling,
    SafetyGate,
)
from services.safety.latch import EstopLatch
from services.safety.policy import JOINTS_STAMP, START_TOLERANCE, SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel, load_world

WORLD = load_world()
HERE = Pose2D(x=6.0, y=1.2)
TICK = 0.02  # the heartbeat's period at 50 Hz
TOKEN = "operator-token"


class FakeClock:
    """The gate's clock: it reads what the test set, and moves only when told."""

    def __init__(self, now: float = 0.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now

    def set(self, now: float) -> None:
        self.now = now

    def advance(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture(scope="module")
def policy() -> SafetyPolicy:
    arm = ArmModel(WORLD.robot.arm_urdf)
    return SafetyPolicy(WorldModel(WORLD), load_policy(None, WORLD.robot, arm, WORLD.keep_out), arm)


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def wall_clock() -> FakeClock:
    return FakeClock(1_700_000_000.0)


@pytest.fixture
def gate(policy: SafetyPolicy, clock: FakeClock, wall_clock: FakeClock) -> SafetyGate:
    return SafetyGate(policy, EstopLatch(TOKEN), clock, wall_clock)


def odom(linear: float = 0.0, angular: float = 0.0, pose: Pose2D = HERE) -> Odometry:
    return Odometry(stamp=0.0, sim_time=0.0, pose=pose, linear_x=linear, angular_z=angular)


def joints(velocity: float) -> JointState:
    n = len(ARM_JOINTS)
    return JointState(stamp=0.0, name=list(ARM_JOINTS), position=list(WORLD.robot.home_joints), velocity=[velocity] * n)


def nobody(gate: SafetyGate) -> None:
    """People reported, none near: full speed from the next tick."""
    gate.humans(PerceivedHumans(stamp=0.0, humans=[]))
    gate.tick()


def latched_by(ruling: Ruling[None]) -> str | None:
    return ruling.events[0].reason if ruling.latched else None


# The watchdog


def test_the_watchdog_waits_exactly_state_max_age_and_trips_one_tick_later(gate: SafetyGate, clock: FakeClock) -> None:
    max_age = gate.policy.policy.monitor.state_max_age
    clock.set(100.0)
    gate.odometry(odom(linear=0.2))
    clock.set(100.0 + max_age)
    at_the_limit = gate.tick()
    assert not at_the_limit.latched and not gate.latch.state.latched
    assert gate.pose() == HERE, "a state exactly state_max_age old still counts"
    clock.advance(TICK)
    after = gate.tick()
    assert after.latched and gate.latch.state.source == EstopSource.WATCHDOG
    (event,) = after.events
    assert (event.decision, event.rule) == (Decision.LATCHED, Rule.WATCHDOG)
    assert "no odometry for 0.52 s while the base was moving" in event.reason
    assert event.values["age_s"] == pytest.approx(max_age + TICK) and event.values["speed_mps"] == 0.2
    assert gate.pose() is None


def test_the_watchdog_leaves_a_still_robot_alone_however_long_it_is_silent(gate: SafetyGate, clock: FakeClock) -> None:
    gate.odometry(odom())
    gate.joint_state(joints(0.0))
    clock.set(3600.0)
    assert not gate.tick().latched
    assert gate.pose() is None and gate.joint_positions() is None


def test_the_watchdog_trips_on_an_arm_that_stops_reporting_while_moving(gate: SafetyGate, clock: FakeClock) -> None:
    max_age = gate.policy.policy.monitor.state_max_age
    gate.joint_state(joints(0.5))
    clock.set(max_age)
    assert not gate.tick().latched
    clock.advance(TICK)
    after = gate.tick()
    assert after.latched and "no joint states for 0.52 s while the arm was moving" in after.events[0].reason
    assert after.events[0].values["speed_rps"] == 0.5


def test_a_clock_that_jumps_forwards_trips_the_watchdog_at_the_next_tick(gate: SafetyGate, clock: FakeClock) -> None:
    gate.odometry(odom(linear=0.2))
    clock.set(TICK)
    assert not gate.tick().latched
    clock.set(10.0)
    jumped = gate.tick()
    assert jumped.latched and jumped.events[0].values["age_s"] == pytest.approx(10.0)


def test_a_clock_that_jumps_back_neither_trips_nor_blinds_the_watchdog(gate: SafetyGate, clock: FakeClock) -> None:
    max_age = gate.policy.policy.monitor.state_max_age
    clock.set(100.0)
    gate.odometry(odom(linear=0.2))
    # Back by a minute: no time has passed for the gate, so the state is as fresh as it was.
    clock.set(40.0)
    assert not gate.tick().latched
    assert gate.pose() == HERE
    # From there the clock runs on: the silence is measured from the jump, not from where the clock
    # was before it, and trips after state_max_age as always.
    clock.set(40.0 + max_age)
    assert not gate.tick().latched
    clock.advance(TICK)
    after = gate.tick()
    assert after.latched and after.events[0].values["age_s"] == pytest.approx(max_age + TICK)


def test_after_a_clock_jump_back_people_unseen_for_unseen_after_reduce_the_speed(
    gate: SafetyGate, clock: FakeClock
) -> None:
    humans = gate.policy.policy.humans
    far = PerceivedHuman(id="operator", name="operator", pose=Pose2D(x=HERE.x, y=HERE.y + 4.0))
    clock.set(100.0)
    gate.odometry(odom())
    gate.humans(PerceivedHumans(stamp=0.0, humans=[far]))
    gate.tick()
    assert gate.separation.scale == 1.0
    # The clock steps back a minute; the last report of people is as old as it was, and ages from here.
    clock.set(40.0)
    for _ in range(int(humans.unseen_after / TICK)):
        gate.odometry(odom())
        assert gate.tick().events == ()
        clock.advance(TICK)
    clock.set(40.0 + humans.unseen_after + TICK)
    (event,) = gate.tick().events
    assert event.values["scale"] == humans.reduced_speed_scale and "no recent report" in event.reason


def test_a_reading_taken_before_another_threads_cannot_reach_the_gate_after_it(
    gate: SafetyGate, clock: FakeClock
) -> None:
    """The reviewer's case: odometry at 50 Hz while the base moves; a thread takes its reading at
    10.0 and stalls; the clock reaches 10.6 and more odometry comes. Had the late reading reached the
    gate after the others, it would look like the clock stepping back, and the gate's time would
    run 0.6 s ahead for good: the next tick would find the odometry of 10.6 0.62 s old and latch."""
    for i in range(501):
        clock.set(i * TICK)
        gate.odometry(odom(linear=0.2))
    assert clock() == pytest.approx(10.0)
    late = threading.Thread(target=gate.humans, args=(PerceivedHumans(stamp=0.0, humans=[]),))
    read, resume = threading.Event(), threading.Event()
    readings: list[tuple[str, float, bool]] = []

    def stalling() -> float:
        now = clock.now
        readings.append((threading.current_thread().name, now, gate._lock.locked()))
        if threading.current_thread() is late:
            read.set()
            assert resume.wait(5.0)
        return now

    gate._clock = stalling
    late.start()
    assert read.wait(5.0)
    clock.set(10.6)
    moving = threading.Thread(target=gate.odometry, args=(odom(linear=0.2),))
    moving.start()
    resume.set()
    late.join(5.0)
    moving.join(5.0)
    assert [(name, now) for name, now, _ in readings] == [(late.name, 10.0), (moving.name, 10.6)]
    assert all(locked for _, _, locked in readings), "the gate reads its clock under its lock"
    clock.set(10.6 + TICK)
    assert not gate.tick().latched
    assert gate.pose() == HERE


def test_a_moving_robot_that_keeps_reporting_never_trips_the_watchdog(gate: SafetyGate, clock: FakeClock) -> None:
    for i in range(200):
        clock.set(i * TICK)
        gate.odometry(odom(linear=0.2))
        clock.advance(TICK / 2)
        assert not gate.tick().latched


# The teleop ramp


@pytest.fixture
def teleop_gate(gate: SafetyGate) -> SafetyGate:
    nobody(gate)
    assert gate.separation.scale == 1.0
    return gate


def turn(gate: SafetyGate, wanted: float) -> float:
    """Ask teleop to turn in place (safe anywhere) at `wanted`; the rate sent to the robot."""
    gate.odometry(odom())
    ruling = gate.teleop(Twist(angular_z=wanted))
    assert ruling.forward is not None, ruling.events
    return ruling.forward.angular_z


def test_teleop_speeds_up_from_a_stop_by_at_most_a_step_of_acceleration(
    teleop_gate: SafetyGate, clock: FakeClock
) -> None:
    accel = teleop_gate.policy.policy.base.max_angular_acceleration
    clock.set(1.0)
    first = teleop_gate.teleop(Twist(angular_z=1.0))
    assert first.forward == Twist(angular_z=pytest.approx(accel * TELEOP_MAX_STEP))
    (event,) = first.events
    assert (event.decision, event.rule) == (Decision.CLAMPED, Rule.BASE_ACCELERATION)
    assert event.values["requested_rps"] == 1.0
    # The next message speeds up from what was sent, by the time since.
    clock.set(1.05)
    assert turn(teleop_gate, 1.0) == pytest.approx(accel * (TELEOP_MAX_STEP + 0.05))


def test_teleop_ramps_on_exactly_at_the_timeout_and_from_a_stop_one_tick_after(
    teleop_gate: SafetyGate, clock: FakeClock
) -> None:
    accel = teleop_gate.policy.policy.base.max_angular_acceleration
    clock.set(1.0)
    sent = turn(teleop_gate, 1.0)
    # Silent exactly TELEOP_TIMEOUT: the robot still holds the last one; the step is capped.
    clock.set(1.0 + TELEOP_TIMEOUT)
    held = turn(teleop_gate, 1.0)
    assert held == pytest.approx(sent + accel * TELEOP_MAX_STEP)
    # Silent one tick longer: the base has stopped, so the ramp starts from a stop again.
    clock.set(1.0 + 2 * TELEOP_TIMEOUT + TICK)
    stopped = turn(teleop_gate, 1.0)
    assert stopped == pytest.approx(accel * TELEOP_MAX_STEP)


def test_teleop_after_a_clock_jump_forwards_starts_from_a_stop(teleop_gate: SafetyGate, clock: FakeClock) -> None:
    accel = teleop_gate.policy.policy.base.max_angular_acceleration
    clock.set(1.0)
    turn(teleop_gate, 1.0)
    clock.set(1.05)
    turn(teleop_gate, 1.0)
    clock.set(500.0)
    nobody(teleop_gate)
    assert turn(teleop_gate, 1.0) == pytest.approx(accel * TELEOP_MAX_STEP)


def test_teleop_after_a_clock_jump_back_speeds_up_from_where_it_was(teleop_gate: SafetyGate, clock: FakeClock) -> None:
    accel = teleop_gate.policy.policy.base.max_angular_acceleration
    clock.set(1.0)
    sent = turn(teleop_gate, 1.0)
    # Back a minute, no time has passed for the gate: no speed-up, and no negative step either.
    clock.set(-59.0)
    assert turn(teleop_gate, 1.0) == pytest.approx(sent)
    # Time runs on from there: 0.05 s later, 0.05 s of acceleration more.
    clock.advance(0.05)
    assert turn(teleop_gate, 1.0) == pytest.approx(sent + accel * 0.05)
    assert turn(teleop_gate, 0.1) == pytest.approx(0.1), "slowing down is never limited"


def test_slowing_down_is_never_ramped(teleop_gate: SafetyGate, clock: FakeClock) -> None:
    clock.set(1.0)
    while turn(teleop_gate, 1.2) < 1.2 - 1e-9:
        clock.advance(0.05)
    clock.advance(0.01)
    assert turn(teleop_gate, 0.0) == 0.0


def test_a_stop_sent_on_any_path_is_where_teleop_ramps_from(teleop_gate: SafetyGate, clock: FakeClock) -> None:
    accel = teleop_gate.policy.policy.base.max_angular_acceleration
    clock.set(1.0)
    while turn(teleop_gate, 1.0) < 1.0 - 1e-9:
        clock.advance(0.05)
    # A program's command over the limit is refused and the base stopped.
    clock.advance(0.01)
    refused = teleop_gate.cmd_vel(Twist(angular_z=3.0))
    assert refused.forward == Twist() and refused.events[0].decision is Decision.VETOED
    clock.advance(0.01)
    assert turn(teleop_gate, 1.0) == pytest.approx(accel * 0.01)


# Repeated vetoes


def test_vetoes_repeated_within_a_second_are_one_event_and_then_a_count(gate: SafetyGate, clock: FakeClock) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"))
    first = gate.cmd_vel(Twist(angular_z=0.1))
    assert first.forward is None, "nothing is sent while the e-stop is latched"
    (event,) = first.events
    assert event.rule is Rule.ESTOP and "an operator must reset it" in event.reason
    for i in range(1, 50):
        clock.set(i * TICK / 2)
        assert gate.cmd_vel(Twist(angular_z=0.1)).events == ()
    clock.set(REPEAT_WINDOW - 1e-6)
    assert gate.tick().events == (), "the count waits for the window to end"
    clock.set(REPEAT_WINDOW)
    (count,) = gate.tick().events
    assert (count.decision, count.rule, count.values) == (Decision.VETOED, Rule.ESTOP, {"count": 49.0})
    assert count.reason.startswith("49 more vetoed like this in the last 1.0 s: e-stop latched by operator")
    clock.advance(TICK)
    assert gate.tick().events == ()
    # The next refusal starts a new window, with its own event.
    clock.advance(TICK)
    assert len(gate.cmd_vel(Twist(angular_z=0.1)).events) == 1


def test_a_window_no_tick_closed_is_counted_before_the_next_veto(gate: SafetyGate, clock: FakeClock) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"))
    gate.cmd_vel(Twist())
    clock.set(0.5)
    gate.cmd_vel(Twist())
    clock.set(REPEAT_WINDOW + 0.01)
    count, veto = gate.cmd_vel(Twist()).events
    assert count.values == {"count": 1.0} and "count" not in veto.values
    clock.set(REPEAT_WINDOW + 0.02)
    assert gate.tick().events == ()


def test_a_lone_veto_is_not_followed_by_a_count(gate: SafetyGate, clock: FakeClock) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"))
    gate.cmd_vel(Twist())
    clock.set(REPEAT_WINDOW + TICK)
    assert gate.tick().events == ()


def test_each_stream_and_rule_is_grouped_on_its_own(gate: SafetyGate, clock: FakeClock) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"))
    for now in (0.0, 0.1, 0.2):
        clock.set(now)
        gate.cmd_vel(Twist())
        gate.teleop(Twist())
    clock.set(REPEAT_WINDOW)
    counts = {e.key: e.values["count"] for e in gate.tick().events}
    assert counts == {keys.CMD_VEL.path: 2.0, keys.TELEOP_CMD_VEL.path: 2.0}


def test_over_the_rate_the_base_is_stopped_and_the_refusals_grouped(gate: SafetyGate, clock: FakeClock) -> None:
    nobody(gate)
    gate.odometry(odom())
    rate = gate.policy.policy.rate
    burst = int(rate.max_cmd_vel_per_second * rate.burst_seconds)
    for _ in range(burst):
        assert gate.cmd_vel(Twist(angular_z=0.1)).forward == Twist(angular_z=0.1)
    over = gate.cmd_vel(Twist(angular_z=0.1))
    assert over.forward == Twist(), "over the rate, the base is stopped"
    assert over.events[0].rule is Rule.COMMAND_RATE
    assert all(gate.cmd_vel(Twist(angular_z=0.1)).events == () for _ in range(9))
    clock.set(REPEAT_WINDOW)
    (count,) = gate.tick().events
    assert count.rule is Rule.COMMAND_RATE and count.values == {"count": 9.0}


# The speed allowed near people


def test_the_speed_goes_down_at_once_and_back_up_with_the_release_margin(gate: SafetyGate, clock: FakeClock) -> None:
    humans = gate.policy.policy.humans
    front = WORLD.robot.base_size.x / 2

    def stand(gap: float) -> Ruling[None]:
        gate.odometry(odom())
        # The arm stowed, its hand over the base: the gap is the footprint's (unknown joints count
        # as the arm held out).
        gate.joint_state(joints(0.0))
        body = HERE.x + front + humans.person_radius + gap
        person = PerceivedHuman(id="operator", name="operator", pose=Pose2D(x=body, y=HERE.y))
        gate.humans(PerceivedHumans(stamp=0.0, humans=[person]))
        # Earlier reports still count for unseen_after: tick once they are all of this one.
        return gate.tick()

    nobody(gate)
    clock.set(0.1)
    slowed = stand(humans.slow_distance - 0.05)
    (event,) = slowed.events
    assert (event.decision, event.rule, event.key) == (Decision.LIMITED, Rule.HUMAN_SEPARATION, keys.HEARTBEAT.path)
    assert event.values == {
        "scale": humans.reduced_speed_scale,
        "distance_m": pytest.approx(humans.slow_distance - 0.05),
    }
    clock.advance(humans.unseen_after + TICK)
    assert stand(humans.slow_distance + humans.release_margin / 2).events == (), "the speed went up too soon"
    clock.advance(humans.unseen_after + TICK)
    assert stand(humans.slow_distance + humans.release_margin + 0.05).events[0].values["scale"] == 1.0
    status = gate.status(seq=7, stamp=123.0)
    assert (status.seq, status.stamp, status.speed_scale) == (7, 123.0, 1.0)
    assert status.max_linear_speed == gate.policy.max_linear


def test_without_a_report_of_people_for_unseen_after_the_speed_is_reduced(gate: SafetyGate, clock: FakeClock) -> None:
    unseen = gate.policy.policy.humans.unseen_after
    nobody(gate)
    clock.set(unseen)
    assert gate.tick().events == (), "a report exactly unseen_after old still counts"
    clock.advance(TICK)
    (event,) = gate.tick().events
    assert event.values["scale"] == gate.policy.policy.humans.reduced_speed_scale
    assert "no recent report" in event.reason


def test_a_separation_that_cannot_be_computed_pauses_the_robot(
    gate: SafetyGate, clock: FakeClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    nobody(gate)

    def broken(t: float) -> None:
        raise RuntimeError("geometry went wrong")

    monkeypatch.setattr(gate, "_find_separation", broken)
    clock.set(TICK)
    (event,) = gate.tick().events
    assert event.values["scale"] == 0.0 and "could not be computed: geometry went wrong" in event.reason
    assert gate.status(1, 0.0).max_linear_speed == 0.0


# The monitors, the latch, goals


def test_a_base_measured_over_the_limit_trip_after_times_latches_once(gate: SafetyGate, clock: FakeClock) -> None:
    nobody(gate)
    trip_after = gate.policy.policy.monitor.trip_after
    rulings = []
    for i in range(trip_after + 2):
        clock.set(0.1 + i * TICK)
        rulings.append(gate.odometry(odom(linear=1.0)))
    assert [r.latched for r in rulings] == [False] * (trip_after - 1) + [True, False, False]
    latched = rulings[trip_after - 1]
    assert latched.events[0].rule is Rule.MONITOR_SPEED and latched.events[0].values["speed_mps"] == 1.0
    assert gate.latch.state.source == EstopSource.MONITOR


def test_the_latch_rules_once_and_only_the_operator_token_clears_it(gate: SafetyGate, clock: FakeClock) -> None:
    pressed = gate.estop(EStop(source=EstopSource.AGENT, reason="stop"))
    assert pressed.latched and latched_by(pressed) == "by agent: stop"
    clock.set(0.1)
    again = gate.estop(EStop(source=EstopSource.OPERATOR, reason="again"))
    assert not again.latched and again.events[0].values["already_latched"] == 1.0
    assert gate.latch.state.source == EstopSource.AGENT and gate.latch.state.reason == "stop"
    wrong = gate.reset(ResetRequest(operator="mallory", token="guess"))
    assert not wrong.reset and not wrong.forward.ok and gate.latch.state.latched
    assert wrong.events[0].command == ResetRequest(operator="mallory", token="***")
    right = gate.reset(ResetRequest(operator="alice", token=TOKEN))
    assert right.reset and right.forward.ok and not gate.latch.state.latched
    assert right.events[0].decision is Decision.RESET and TOKEN not in repr(right.events)


def test_the_latch_is_stamped_with_the_gates_wall_clock(gate: SafetyGate, wall_clock: FakeClock) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"))
    assert gate.latch.state.stamp == 1_700_000_000.0
    wall_clock.advance(60.0)
    gate.reset(ResetRequest(operator="alice", token=TOKEN))
    assert gate.latch.state.stamp == 1_700_000_060.0


def test_an_estop_that_cannot_be_read_latches(gate: SafetyGate) -> None:
    ruling = gate.unreadable_estop(12, "truncated")
    assert ruling.latched and gate.latch.state.source == "unknown"
    assert "could not be read (12 bytes): truncated" in ruling.events[0].reason


def test_a_latch_stops_the_base_and_teleop_ramps_from_that_stop(gate: SafetyGate, clock: FakeClock) -> None:
    nobody(gate)
    accel = gate.policy.policy.base.max_angular_acceleration
    clock.set(0.1)
    while turn(gate, 1.0) < 1.0 - 1e-9:
        clock.advance(0.05)
    clock.advance(0.01)
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"))
    gate.reset(ResetRequest(operator="alice", token=TOKEN))
    clock.advance(0.01)
    assert turn(gate, 1.0) == pytest.approx(accel * 0.01)


def test_a_goal_while_latched_is_refused_as_an_estop(gate: SafetyGate) -> None:
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"))
    ruling = gate.navigate(SendGoal(goal_id="g1", goal=NavigateToPoseGoal(pose=HERE)))
    assert isinstance(ruling.forward, GoalResponse) and not ruling.forward.accepted
    assert ruling.forward.kind is not None and ruling.forward.kind.value == "estop"
    assert ruling.forward.reason.startswith("vetoed by safety: e-stop latched by operator")


def test_an_approved_goal_is_forwarded_as_checked(gate: SafetyGate) -> None:
    gate.odometry(odom())
    ruling = gate.navigate(SendGoal(goal_id="g1", goal=NavigateToPoseGoal(pose=Pose2D(x=6.5, y=1.2))))
    assert isinstance(ruling.forward, SendGoal) and ruling.forward.goal_id == "g1"
    assert ruling.forward.goal.start == HERE, "the route was checked from here"
    assert ruling.events[0].decision is Decision.APPROVED
    assert ruling.forward.goal.max_speed == gate.policy.max_linear, "no speed given: the limit filled in"


# A trajectory whose first point seems to jump

HOME = list(WORLD.robot.home_joints)
# Where the last motion took the arm, while the latest joint state here still says HOME.
STOPPED = [HOME[0], HOME[1] + 2 * START_TOLERANCE, *HOME[2:]]


def arm_at(q: list[float], stamp: float = 0.0) -> JointState:
    return JointState(stamp=stamp, name=list(ARM_JOINTS), position=q)


def from_stopped() -> SendGoal[FollowJointTrajectoryGoal]:
    points = [
        TrajectoryPoint(positions=STOPPED, time_from_start=0.0),
        TrajectoryPoint(positions=HOME, time_from_start=2.0),
    ]
    return SendGoal(goal_id="t1", goal=FollowJointTrajectoryGoal(joint_names=list(ARM_JOINTS), points=points))


def test_a_start_that_seems_to_jump_passes_on_fresh_joints_without_a_second_rate_token(gate: SafetyGate) -> None:
    gate.odometry(odom())
    gate.joint_state(arm_at(HOME, stamp=10.0))
    first = gate.trajectory(from_stopped())
    assert isinstance(first.forward, GoalResponse) and not first.forward.accepted
    assert first.fresh_joints_may_pass and "jump_rad" in first.events[0].values
    # Each decision names the joint state it rested on (`tether recheck` checks from that one).
    assert first.events[0].values[JOINTS_STAMP] == 10.0
    rate = gate.policy.policy.rate
    for _ in range(int(max(1.0, rate.max_goals_per_second * rate.burst_seconds)) - 1):
        gate.trajectory(from_stopped())  # the rest of the burst, on the same instant: no token left
    gate.joint_state(arm_at(STOPPED, stamp=10.02))
    again = gate.trajectory(from_stopped(), again=True)
    assert isinstance(again.forward, SendGoal) and again.forward.goal_id == "t1"
    assert again.events[0].decision is Decision.APPROVED and not again.fresh_joints_may_pass
    assert again.events[0].values[JOINTS_STAMP] == 10.02
    over = gate.trajectory(from_stopped())
    assert over.events[0].rule is Rule.COMMAND_RATE, "the bucket was empty: asking again took no token"


def test_a_start_that_still_jumps_on_fresh_joints_is_refused_for_good(gate: SafetyGate) -> None:
    gate.odometry(odom())
    gate.joint_state(arm_at(HOME))
    assert gate.trajectory(from_stopped()).fresh_joints_may_pass
    gate.joint_state(arm_at(HOME))
    again = gate.trajectory(from_stopped(), again=True)
    assert isinstance(again.forward, GoalResponse) and not again.forward.accepted
    assert "would jump" in again.forward.reason and not again.fresh_joints_may_pass


def test_an_estop_latched_while_waiting_for_fresh_joints_refuses_the_goal_asked_again(gate: SafetyGate) -> None:
    gate.odometry(odom())
    gate.joint_state(arm_at(HOME))
    assert gate.trajectory(from_stopped()).fresh_joints_may_pass
    gate.estop(EStop(source=EstopSource.OPERATOR, reason="test"))
    gate.joint_state(arm_at(STOPPED))
    again = gate.trajectory(from_stopped(), again=True)
    assert isinstance(again.forward, GoalResponse) and not again.forward.accepted
    assert again.forward.kind is not None and again.forward.kind.value == "estop"
    assert again.events[0].rule is Rule.ESTOP


def test_reset_attempts_are_rate_limited_per_operator_saying_when_to_retry(gate: SafetyGate, clock: FakeClock) -> None:
    gate.estop(EStop(source="test", reason="stop"))
    for _ in range(5):
        assert not gate.reset(ResetRequest(operator="mallory", token="guess")).forward.ok
        clock.advance(1.0)
    # The sixth wrong one within a minute is refused saying when to try again.
    limited = gate.reset(ResetRequest(operator="mallory", token="guess"))
    assert not limited.forward.ok and gate.latch.state.latched
    assert "too many attempts (at most 5 a minute per operator" in limited.forward.message
    assert limited.forward.message.endswith("try again in 55 s"), limited.forward.message
    [event] = limited.events
    assert event.decision is Decision.VETOED and event.rule is Rule.OPERATOR
    assert event.values["retry_after_s"] == pytest.approx(55.0)
    assert "guess" not in repr(event) and TOKEN not in repr(event)
    # Another operator is not held up by mallory's attempts, nor is the right token under that name.
    assert gate.reset(ResetRequest(operator="alice", token=TOKEN)).forward.ok
    gate.estop(EStop(source="test", reason="again"))
    assert gate.reset(ResetRequest(operator="mallory", token=TOKEN)).forward.ok
    gate.estop(EStop(source="test", reason="again"))
    clock.advance(55.0)  # mallory's first attempt has left the window
    assert "too many" not in gate.reset(ResetRequest(operator="mallory", token="guess")).forward.message


def test_many_names_do_not_get_around_the_reset_limit(gate: SafetyGate, clock: FakeClock) -> None:
    gate.estop(EStop(source="test", reason="stop"))
    for i in range(15):
        assert "too many" not in gate.reset(ResetRequest(operator=f"name{i}", token="guess")).forward.message
    refused = gate.reset(ResetRequest(operator="fresh", token="guess"))
    assert not refused.forward.ok and "15 for all" in refused.forward.message
    clock.advance(60.0)
    assert "too many" not in gate.reset(ResetRequest(operator="fresh", token="guess")).forward.message


def test_made_up_names_filling_the_shared_limit_do_not_lock_out_the_operator(
    gate: SafetyGate, clock: FakeClock
) -> None:
    gate.estop(EStop(source="test", reason="stop"))
    for i in range(15):
        gate.reset(ResetRequest(operator=f"made-up-{i}", token="guess"))
        clock.advance(1.0)
    assert "15 for all" in gate.reset(ResetRequest(operator="alice", token="guess")).forward.message
    right = gate.reset(ResetRequest(operator="alice", token=TOKEN))
    assert right.reset and right.forward.ok and not gate.latch.state.latched
    # Right resets are never counted: the operator may reset as often as the robot needs.
    for _ in range(10):
        gate.estop(EStop(source="test", reason="again"))
        assert gate.reset(ResetRequest(operator="alice", token=TOKEN)).forward.ok
    # Wrong ones sent under the operator's name (it is in every event) fill that name's limit, and
    # hold up more wrong ones, never the operator with the right token (a review's finding: that
    # locked the real operator out of a reset or a pause for as long as someone kept it up).
    clock.advance(60.0)  # the made-up names' attempts have left the window
    for _ in range(5):
        assert "too many" not in gate.reset(ResetRequest(operator="alice", token="guess")).forward.message
    limited = gate.reset(ResetRequest(operator="alice", token="guess"))
    assert not limited.forward.ok and "at most 5 a minute per operator" in limited.forward.message
    gate.estop(EStop(source="test", reason="again"))
    right = gate.reset(ResetRequest(operator="alice", token=TOKEN))
    assert right.reset and right.forward.ok and not gate.latch.state.latched
