"""What safety watches while the robot runs, at each limit: command rates, separation from people,
measured speeds against the allowed ones (and the allowance decaying after the limit drops).

Pure logic on numbers and timestamps; the numbers are the default policy file's.
"""

from __future__ import annotations

import msgspec
import pytest

from schemas.common import Pose2D
from schemas.safety import Rule
from services.safety.monitor import MotionMonitor, Person, RateLimit, SpeedEnvelope, nearest_person, separation
from services.safety.policyfile import DEFAULT_POLICY, MonitorPolicy, Policy
from services.worldmodel import load_world

POLICY = msgspec.toml.decode(DEFAULT_POLICY.read_bytes(), type=Policy)
HUMANS = POLICY.humans
MONITOR = POLICY.monitor
ROBOT = load_world().robot
SIZE = (ROBOT.base_size.x, ROBOT.base_size.y)  # 0.6 m long, 0.5 m wide
EPS = 1e-3
V = POLICY.base.max_linear_speed
W = POLICY.base.max_angular_speed
JOINT_SPEED = 1.5
# As the node sets it: the allowance falls at the base's deceleration.
DECAY = POLICY.base.max_linear_acceleration / V


def allowed(limit: float, scale: float = 1.0) -> float:
    return limit * scale * (1.0 + MONITOR.speed_tolerance) + MONITOR.speed_slack


def monitor(policy: MonitorPolicy = MONITOR) -> MotionMonitor:
    return MotionMonitor(policy, V, W, {"panda_joint1": JOINT_SPEED, "panda_joint7": JOINT_SPEED}, DECAY)


# command_rate


@pytest.mark.parametrize(
    "rate", [POLICY.rate.max_goals_per_second, POLICY.rate.max_cmd_vel_per_second], ids=["goals", "cmd_vel"]
)
def test_a_burst_of_capacity_commands_passes_and_the_next_is_refused(rate: float) -> None:
    burst = POLICY.rate.burst_seconds
    limit = RateLimit(rate, burst)
    capacity = round(rate * burst)
    assert limit.capacity == capacity
    assert all(limit.allow(0.0) for _ in range(capacity))
    assert not limit.allow(0.0)
    # A token comes back every 1/rate seconds: not a moment before.
    assert not limit.allow(1.0 / rate - 1e-6)
    assert limit.allow(1.0 / rate)
    assert not limit.allow(1.0 / rate)


def test_commands_at_the_rate_pass_indefinitely_and_faster_ones_are_refused_once_the_burst_is_spent() -> None:
    rate, burst = 8.0, 0.5  # 1/8 s is exact in binary: no rounding at the boundary
    steady = RateLimit(rate, burst)
    assert all(steady.allow(i / rate) for i in range(1000))
    fast = RateLimit(rate, burst)
    results = [fast.allow(i / (rate * 1.25)) for i in range(100)]
    assert all(results[:4]) and not all(results)
    # Over a long run the faster stream gets through at the rate, plus the burst.
    assert sum(results) == pytest.approx(4 + rate * 99 / (rate * 1.25), abs=1.5)


def test_an_idle_bucket_fills_only_to_its_capacity() -> None:
    limit = RateLimit(10.0, 0.5)
    assert limit.allow(0.0)
    passed = [limit.allow(1000.0) for _ in range(10)]
    assert passed == [True] * 5 + [False] * 5


def test_a_bucket_smaller_than_one_command_still_lets_one_through() -> None:
    limit = RateLimit(1.0, 0.5)
    assert limit.capacity == 1.0
    assert limit.allow(0.0) and not limit.allow(0.5)
    assert limit.allow(1.0)


# human_separation


@pytest.mark.parametrize(
    ("distance", "scale"),
    [
        (HUMANS.slow_distance + EPS, 1.0),
        (HUMANS.slow_distance, HUMANS.reduced_speed_scale),
        (HUMANS.slow_distance - EPS, HUMANS.reduced_speed_scale),
        (HUMANS.stop_distance + EPS, HUMANS.reduced_speed_scale),
        (HUMANS.stop_distance, 0.0),
        (HUMANS.stop_distance - EPS, 0.0),
        (0.0, 0.0),
    ],
    ids=["beyond-D", "at-D", "inside-D", "beyond-d", "at-d", "inside-d", "touching"],
)
def test_the_speed_scale_at_each_separation_boundary(distance: float, scale: float) -> None:
    person = Person("operator", 0.0, 0.0)
    verdict = separation((distance, person), True, HUMANS)
    assert verdict.scale == scale
    assert verdict.distance == distance and verdict.person == "operator"
    if scale == 1.0:
        assert verdict.reason == ""
    else:
        assert verdict.reason.startswith(f"operator is {distance:.2f} m away, within ")
        assert ("paused" if scale == 0.0 else "reduced speed") in verdict.reason


def test_with_no_recent_report_of_people_the_speed_is_reduced_wherever_they_were() -> None:
    far = (HUMANS.slow_distance + 10.0, Person("operator", 20.0, 0.0))
    for nearest in (far, None):
        verdict = separation(nearest, False, HUMANS)
        assert verdict.scale == HUMANS.reduced_speed_scale
        assert "no recent report" in verdict.reason
    assert separation(None, True, HUMANS).scale == 1.0


@pytest.mark.parametrize(
    ("yaw", "person", "distance"),
    [
        (0.0, (1.0, 0.0), 1.0 - SIZE[0] / 2),  # ahead: from the front edge, 0.7 m
        (0.0, (0.0, 1.0), 1.0 - SIZE[1] / 2),  # beside: from the side, 0.75 m
        (0.0, (-1.0, 0.0), 1.0 - SIZE[0] / 2),  # behind
        (1.5707963267948966, (0.0, 1.0), 1.0 - SIZE[0] / 2),  # turned left: the front faces +y
        (1.5707963267948966, (1.0, 0.0), 1.0 - SIZE[1] / 2),
        (0.0, (0.1, 0.1), 0.0),  # standing inside the footprint
    ],
)
def test_the_distance_to_a_person_is_from_the_footprint_not_the_centre(
    yaw: float, person: tuple[float, float], distance: float
) -> None:
    found = nearest_person(Pose2D(x=0.0, y=0.0, yaw=yaw), SIZE, None, [Person("p", *person)])
    assert found is not None
    assert found[0] == pytest.approx(distance, abs=1e-9)


def test_a_person_beyond_d_from_the_centre_but_within_it_from_the_front_edge_slows_the_robot() -> None:
    here = Pose2D(x=5.0, y=5.0)
    front = SIZE[0] / 2
    for gap, scale in ((HUMANS.slow_distance + EPS, 1.0), (HUMANS.slow_distance - EPS, HUMANS.reduced_speed_scale)):
        person = Person("p", here.x + front + gap, here.y)
        found = nearest_person(here, SIZE, None, [person])
        assert found is not None and found[0] == pytest.approx(gap)
        assert separation(found, True, HUMANS).scale == scale


def test_the_hand_counts_when_it_is_nearer_than_the_base_and_the_nearest_person_wins() -> None:
    here = Pose2D(x=0.0, y=0.0)
    near, far = Person("near", 1.0, 0.0), Person("far", 0.0, 3.0)
    found = nearest_person(here, SIZE, (0.9, 0.0), [far, near])
    assert found is not None
    assert found[1] is near and found[0] == pytest.approx(0.1)
    assert nearest_person(here, SIZE, None, []) is None


# monitor_speed


@pytest.mark.parametrize(
    ("linear", "angular"),
    [(allowed(V) - EPS, 0.0), (-(allowed(V) - EPS), 0.0), (0.0, allowed(W) - EPS), (0.0, -(allowed(W) - EPS))],
)
def test_measured_base_speed_just_within_the_allowance_never_trips(linear: float, angular: float) -> None:
    watch = monitor()
    assert all(watch.base(i * 0.01, linear, angular, 1.0) is None for i in range(200))


@pytest.mark.parametrize(
    ("linear", "angular"),
    [(allowed(V) + EPS, 0.0), (-(allowed(V) + EPS), 0.0), (0.0, allowed(W) + EPS), (0.0, -(allowed(W) + EPS))],
)
def test_measured_base_speed_just_over_the_allowance_trips_after_trip_after_samples(
    linear: float, angular: float
) -> None:
    watch = monitor()
    n = MONITOR.trip_after
    assert all(watch.base(i * 0.01, linear, angular, 1.0) is None for i in range(n - 1))
    trip = watch.base((n - 1) * 0.01, linear, angular, 1.0)
    assert trip is not None and trip.rule is Rule.MONITOR_SPEED
    assert trip.values == {
        "speed_mps": linear,
        "turn_rps": angular,
        "allowed_mps": pytest.approx(allowed(V)),
        "allowed_rps": pytest.approx(allowed(W)),
    }
    assert f"allowed {allowed(V):.2f} m/s, {allowed(W):.2f} rad/s" in trip.reason


def test_one_sample_within_the_allowance_restarts_the_count() -> None:
    watch = monitor()
    over, under = allowed(V) + EPS, allowed(V) - EPS
    samples = [over] * (MONITOR.trip_after - 1) + [under] + [over] * (MONITOR.trip_after - 1)
    assert all(watch.base(i * 0.01, v, 0.0, 1.0) is None for i, v in enumerate(samples))
    assert watch.base(1.0, over, 0.0, 1.0) is not None


def test_the_allowance_follows_the_separation_scale() -> None:
    scale = HUMANS.reduced_speed_scale
    reduced = monitor(MonitorPolicy(trip_after=1))
    assert reduced.base(0.0, allowed(V, scale) - EPS, 0.0, scale) is None
    trip = reduced.base(0.01, allowed(V, scale) + EPS, 0.0, scale)
    assert trip is not None and trip.values["allowed_mps"] == pytest.approx(allowed(V, scale))
    paused = monitor(MonitorPolicy(trip_after=1))
    assert paused.base(0.0, MONITOR.speed_slack, 0.0, 0.0) is None  # only the slack is left
    assert paused.base(0.01, MONITOR.speed_slack + EPS, 0.0, 0.0) is not None


# monitor_joint_speed


def test_measured_joint_speed_just_within_the_allowance_never_trips_and_just_over_trips() -> None:
    watch = monitor()
    within = {"panda_joint1": allowed(JOINT_SPEED) - EPS, "panda_joint7": -(allowed(JOINT_SPEED) - EPS)}
    assert all(watch.joints(i * 0.01, within, 1.0) is None for i in range(200))
    over = {"panda_joint1": allowed(JOINT_SPEED) + EPS, "panda_joint7": -(allowed(JOINT_SPEED) + 2 * EPS)}
    n = MONITOR.trip_after
    assert all(watch.joints(2.0 + i * 0.01, over, 1.0) is None for i in range(n - 1))
    trip = watch.joints(3.0, over, 1.0)
    assert trip is not None and trip.rule is Rule.MONITOR_JOINT_SPEED
    # The worst joint is named.
    assert trip.reason.startswith("panda_joint7 was measured at ")
    assert trip.values == {"speed_rps": over["panda_joint7"], "allowed_rps": pytest.approx(allowed(JOINT_SPEED))}


def test_joints_with_no_limit_are_not_monitored() -> None:
    watch = monitor(MonitorPolicy(trip_after=1))
    assert watch.joints(0.0, {"panda_finger_joint1": 100.0}, 1.0) is None


# After the limit drops, the allowance decays at the deceleration rate


def test_the_envelope_falls_at_its_decay_rate_to_the_new_scale_and_rises_at_once() -> None:
    envelope = SpeedEnvelope(2.5)
    assert envelope.update(0.0, 1.0) == 1.0
    assert envelope.update(0.1, 0.4) == pytest.approx(0.75)
    assert envelope.update(0.2, 0.4) == pytest.approx(0.5)
    assert envelope.update(0.3, 0.4) == 0.4
    assert envelope.update(0.4, 1.0) == 1.0
    # A first report sets the scale at once: there is no earlier speed to slow from.
    assert SpeedEnvelope(2.5).update(5.0, 0.0) == 0.0


@pytest.mark.parametrize("after", [0.01, 0.04, 0.1])
def test_right_after_the_limit_drops_the_allowance_is_the_decayed_one(after: float) -> None:
    scale = max(HUMANS.reduced_speed_scale, 1.0 - DECAY * after)
    edge = allowed(V, scale)
    for speed, trips in ((edge - EPS, False), (edge + EPS, True)):
        watch = monitor(MonitorPolicy(trip_after=1))
        assert watch.base(0.0, 0.0, 0.0, 1.0) is None
        trip = watch.base(after, speed, 0.0, HUMANS.reduced_speed_scale)
        assert (trip is not None) == trips
        if trip is not None:
            assert trip.values["allowed_mps"] == pytest.approx(edge)


def test_full_speed_is_allowed_just_after_the_drop_but_not_once_the_robot_had_time_to_slow() -> None:
    watch = monitor()
    reduced = HUMANS.reduced_speed_scale
    assert watch.base(0.0, V, 0.0, 1.0) is None
    # The full limit stays allowed while the envelope is above (V - slack) / (V * (1 + tolerance)).
    still_ok = (1.0 - (V - MONITOR.speed_slack) / (V * (1.0 + MONITOR.speed_tolerance))) / DECAY
    times = [i * 0.005 for i in range(1, 200)]
    trips = [t for t in times if watch.base(t, V, 0.0, reduced) is not None]
    assert trips, "full speed long after the limit dropped must trip"
    first_over = min(t for t in times if t > still_ok)
    assert trips[0] == pytest.approx(first_over + (MONITOR.trip_after - 1) * 0.005)
    # The arm's allowance decays the same way.
    arm = monitor()
    assert arm.joints(0.0, {"panda_joint1": JOINT_SPEED}, 1.0) is None
    assert arm.joints(0.005, {"panda_joint1": JOINT_SPEED}, reduced) is None
    assert any(arm.joints(t, {"panda_joint1": JOINT_SPEED}, reduced) is not None for t in times[1:])
