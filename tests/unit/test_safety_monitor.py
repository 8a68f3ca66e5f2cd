"""What safety watches while the robot runs, at each limit: command rates, separation from people
(and the reports of where they are), measured speeds against the allowed ones (and the allowance
holding for the reaction time, then decaying, after the limit drops).

Pure logic on numbers and timestamps; the numbers are the default policy file's.
"""

from __future__ import annotations

import sys
import threading

import msgspec
import pytest

from schemas.common import Pose2D
from schemas.safety import Rule
from services.safety.monitor import (
    MotionMonitor,
    PeopleReports,
    Person,
    RateLimit,
    SpeedEnvelope,
    nearest_person,
    separation,
)
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
REACTION = MONITOR.reaction_time
# Long enough after a drop, even to a stop, for the allowance to have reached the new scale.
SETTLED = REACTION + 1.0 / DECAY + 0.1


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


def test_a_clock_going_back_neither_drains_nor_refills_the_bucket() -> None:
    rate = 8.0  # 1/8 s is exact in binary
    limit = RateLimit(rate, 0.5)
    assert limit.allow(100.0)
    # Earlier than the last command: the tokens left are still there, no fewer.
    assert all(limit.allow(0.0) for _ in range(3))
    assert not limit.allow(0.0)
    # Nor does coming back to the last time refill the bucket: time is counted from the latest.
    assert not limit.allow(50.0)
    assert not limit.allow(100.0)
    assert limit.allow(100.0 + 1.0 / rate)
    assert not limit.allow(100.0 + 1.0 / rate)


def test_a_bucket_shared_by_threads_lets_exactly_its_capacity_through() -> None:
    threads, each, rate = 8, 300, 1000.0
    previous = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible, to meet any race
    try:
        for _ in range(3):
            limit = RateLimit(rate, 1.0)
            passed: list[int] = []
            start = threading.Barrier(threads)

            def spend(limit: RateLimit = limit, passed: list[int] = passed, start: threading.Barrier = start) -> None:
                start.wait()
                passed.append(sum(limit.allow(0.0) for _ in range(each)))

            workers = [threading.Thread(target=spend) for _ in range(threads)]
            for worker in workers:
                worker.start()
            for worker in workers:
                worker.join()
            assert sum(passed) == limit.capacity == rate
    finally:
        sys.setswitchinterval(previous)


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


def test_a_looser_scale_waits_for_the_release_margin_and_a_stricter_one_does_not() -> None:
    person = Person("operator", 0.0, 0.0)
    margin = HUMANS.release_margin
    assert margin > 2 * EPS
    reduced, full = HUMANS.reduced_speed_scale, 1.0
    steps = [
        # (distance, scale in force, scale now)
        (HUMANS.slow_distance - EPS, full, reduced),  # tighter at once
        (HUMANS.slow_distance + EPS, reduced, reduced),  # stepped back past D: not yet
        (HUMANS.slow_distance + margin - EPS, reduced, reduced),
        (HUMANS.slow_distance + margin + EPS, reduced, full),  # past the margin
        (HUMANS.slow_distance + EPS, full, full),  # from full speed, D itself counts again
        (HUMANS.stop_distance - EPS, reduced, 0.0),
        (HUMANS.stop_distance + EPS, 0.0, 0.0),  # paused until the margin beyond d
        (HUMANS.stop_distance + margin + EPS, 0.0, reduced),
        (HUMANS.stop_distance - EPS, full, 0.0),  # from full speed straight to paused
    ]
    for distance, current, expected in steps:
        verdict = separation((distance, person), True, HUMANS, current)
        assert verdict.scale == expected, f"{distance:.3f} m from {current}: {verdict}"
    held = separation((HUMANS.slow_distance + EPS, person), True, HUMANS, reduced)
    assert f"within {HUMANS.slow_distance + margin:g} m" in held.reason


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


@pytest.mark.parametrize("radius", [HUMANS.person_radius, 0.5])
def test_the_distance_is_to_the_persons_body_around_where_they_stand(radius: float) -> None:
    here = Pose2D(x=0.0, y=0.0)
    front = SIZE[0] / 2
    person = Person("p", front + 1.0, 0.0)
    found = nearest_person(here, SIZE, None, [person], radius)
    assert found is not None and found[0] == pytest.approx(1.0 - radius)
    # From the hand too, and never below zero when the body touches the robot.
    found = nearest_person(here, SIZE, (front + 0.6, 0.0), [person], radius)
    assert found is not None and found[0] == pytest.approx(max(0.0, 0.4 - radius))
    touching = Person("p", front + radius / 2, 0.0)
    assert nearest_person(here, SIZE, None, [touching], radius) == (0.0, touching)


def test_the_robot_pauses_when_a_persons_body_not_where_they_stand_comes_within_d() -> None:
    here = Pose2D(x=5.0, y=5.0)
    front = SIZE[0] / 2
    radius = HUMANS.person_radius
    assert radius > 2 * EPS
    for gap, scale in (
        (HUMANS.stop_distance + radius + EPS, HUMANS.reduced_speed_scale),
        (HUMANS.stop_distance + radius - EPS, 0.0),
    ):
        found = nearest_person(here, SIZE, None, [Person("p", here.x + front + gap, here.y)], radius)
        assert found is not None and found[0] == pytest.approx(gap - radius)
        assert separation(found, True, HUMANS).scale == scale


# Reports of people: everyone seen within the window counts


def test_with_no_report_within_the_window_where_people_are_is_unknown() -> None:
    window = HUMANS.unseen_after
    reports = PeopleReports(window)
    assert reports.people(0.0) is None
    reports.add(10.0, [])
    assert reports.people(10.0) == [], "a report with nobody in it: nobody, and known"
    assert reports.people(10.0 + window) == []
    assert reports.people(10.0 + window + EPS) is None


def test_an_empty_report_cannot_hide_a_person_another_report_within_the_window_saw() -> None:
    window = HUMANS.unseen_after
    reports = PeopleReports(window)
    alice, bob = Person("alice", 1.0, 0.0), Person("bob", 2.0, 0.0)
    reports.add(10.0, [alice])  # one camera sees alice
    reports.add(10.1, [])  # another sees no one
    assert reports.people(10.1) == [alice]
    reports.add(10.2, [bob])
    assert reports.people(10.2) == [alice, bob]
    # Each report counts for the window from when it came, then no longer.
    assert reports.people(10.0 + window) == [alice, bob]
    assert reports.people(10.0 + window + EPS) == [bob]
    assert reports.people(10.2 + window) == [bob]
    assert reports.people(10.2 + window + EPS) is None


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
    # Once the allowance has had time to fall to the scale (see the envelope below).
    scale = HUMANS.reduced_speed_scale
    reduced = monitor(MonitorPolicy(trip_after=1))
    assert reduced.base(0.0, 0.0, 0.0, scale) is None
    assert reduced.base(SETTLED, allowed(V, scale) - EPS, 0.0, scale) is None
    trip = reduced.base(SETTLED + 0.01, allowed(V, scale) + EPS, 0.0, scale)
    assert trip is not None and trip.values["allowed_mps"] == pytest.approx(allowed(V, scale))
    paused = monitor(MonitorPolicy(trip_after=1))
    assert paused.base(0.0, 0.0, 0.0, 0.0) is None
    assert paused.base(SETTLED, MONITOR.speed_slack, 0.0, 0.0) is None  # only the slack is left
    assert paused.base(SETTLED + 0.01, MONITOR.speed_slack + EPS, 0.0, 0.0) is not None


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


# After the limit drops, the allowance holds for the reaction time, then decays at the deceleration rate


def test_the_envelope_holds_for_the_reaction_time_then_falls_at_its_decay_rate_and_rises_at_once() -> None:
    envelope = SpeedEnvelope(2.5, 0.25)
    assert envelope.update(0.0, 1.0) == 1.0
    # The hold counts from the first update that sees the drop, not from the last one before it.
    assert envelope.update(1.0, 0.4) == 1.0
    assert envelope.update(1.25, 0.4) == 1.0
    assert envelope.update(1.35, 0.4) == pytest.approx(0.75)
    assert envelope.update(1.45, 0.4) == pytest.approx(0.5)
    # At reaction_time + (1 - 0.4) / 2.5 after the drop it is the new scale; just before, a little above.
    assert envelope.update(1.49 - EPS, 0.4) == pytest.approx(0.4 + 2.5 * EPS)
    assert envelope.update(1.49, 0.4) == pytest.approx(0.4)
    assert envelope.update(5.0, 0.4) == 0.4
    assert envelope.update(5.1, 1.0) == 1.0


def test_a_further_drop_gets_its_own_hold_without_undoing_the_fall_under_way() -> None:
    envelope = SpeedEnvelope(2.5, 0.25)
    assert envelope.update(0.0, 1.0) == 1.0
    assert envelope.update(0.0, 0.5) == 1.0
    assert envelope.update(0.35, 0.5) == pytest.approx(0.75)
    assert envelope.update(0.35, 0.25) == pytest.approx(0.75)  # further down: held from 0.75 ...
    assert envelope.update(0.6, 0.25) == pytest.approx(0.5)  # ... while the first fall goes on to 0.5
    assert envelope.update(0.7, 0.25) == pytest.approx(0.5)  # the second fall has just reached 0.5
    assert envelope.update(0.9, 0.25) == 0.25
    assert envelope.update(1.0, 0.5) == 0.5  # a rise applies at once


def test_a_rise_while_the_allowance_is_still_falling_stops_it_at_the_new_scale() -> None:
    envelope = SpeedEnvelope(2.5, 0.25)
    assert envelope.update(0.0, 1.0) == 1.0
    assert envelope.update(2.0, 0.25) == 1.0
    assert envelope.update(2.1, 0.5) == 1.0  # up again, but still below the allowance: the hold goes on
    assert envelope.update(2.35, 0.5) == pytest.approx(0.75)
    assert envelope.update(2.5, 0.5) == 0.5
    assert envelope.update(3.0, 0.5) == 0.5


def test_with_no_reaction_time_the_allowance_falls_from_the_first_update_that_sees_the_drop() -> None:
    envelope = SpeedEnvelope(2.5)
    assert envelope.update(0.0, 1.0) == 1.0
    assert envelope.update(1.0, 0.4) == 1.0
    assert envelope.update(1.1, 0.4) == pytest.approx(0.75)
    assert envelope.update(1.3, 0.4) == 0.4


@pytest.mark.parametrize(
    "after",
    [0.01, REACTION - 0.01, REACTION + 0.04, REACTION + 0.1, REACTION + (1.0 - HUMANS.reduced_speed_scale) / DECAY],
    ids=["just-after", "end-of-hold", "braking", "braking-more", "at-the-new-scale"],
)
def test_after_the_limit_drops_the_allowance_is_full_for_the_reaction_time_then_the_decayed_one(
    after: float,
) -> None:
    reduced = HUMANS.reduced_speed_scale
    scale = max(reduced, 1.0 - DECAY * max(0.0, after - REACTION))
    edge = allowed(V, scale)
    drop = SETTLED  # the last update at full speed was long before: the hold counts from the drop
    for speed, trips in ((edge - EPS, False), (edge + EPS, True)):
        watch = monitor(MonitorPolicy(trip_after=1))
        assert watch.base(0.0, 0.0, 0.0, 1.0) is None
        assert watch.base(drop, 0.0, 0.0, reduced) is None
        trip = watch.base(drop + after, speed, 0.0, reduced)
        assert (trip is not None) == trips
        if trip is not None:
            assert trip.values["allowed_mps"] == pytest.approx(edge)


def test_the_monitors_hold_is_the_policys_reaction_time() -> None:
    reduced = HUMANS.reduced_speed_scale
    for reaction, scale in ((0.0, max(reduced, 1.0 - DECAY * 0.1)), (0.2, 1.0)):
        watch = monitor(MonitorPolicy(trip_after=1, reaction_time=reaction))
        assert watch.base(0.0, 0.0, 0.0, 1.0) is None
        assert watch.base(0.0, 0.0, 0.0, reduced) is None
        trip = watch.base(0.1, V * 2, 0.0, reduced)
        assert trip is not None and trip.values["allowed_mps"] == pytest.approx(allowed(V, scale))


def test_a_speed_a_hair_over_the_decayed_allowance_trips_after_trip_after_samples_once_the_hold_is_over() -> None:
    reduced = HUMANS.reduced_speed_scale
    watch = monitor()
    n = MONITOR.trip_after
    assert watch.base(0.0, V, 0.0, 1.0) is None
    assert watch.base(1.0, V, 0.0, reduced) is None
    # Full speed, however many samples, while the hold lasts.
    hold = [1.0 + k * 0.01 for k in range(1, round(REACTION / 0.01))]
    assert all(watch.base(t, V, 0.0, reduced) is None for t in hold)
    settled = 1.0 + REACTION + (1.0 - reduced) / DECAY
    over = allowed(V, reduced) + EPS
    assert all(watch.base(settled + k * 0.01, over, 0.0, reduced) is None for k in range(n - 1))
    trip = watch.base(settled + (n - 1) * 0.01, over, 0.0, reduced)
    assert trip is not None and trip.rule is Rule.MONITOR_SPEED
    assert trip.values["allowed_mps"] == pytest.approx(allowed(V, reduced))


def test_full_speed_is_allowed_just_after_the_drop_but_not_once_the_robot_had_time_to_slow() -> None:
    watch = monitor()
    reduced = HUMANS.reduced_speed_scale
    step = 0.005
    assert watch.base(0.0, V, 0.0, 1.0) is None

    # The drop is first seen at `step`. The full limit stays allowed for the reaction time, then
    # while the envelope is above (V - slack) / (V * (1 + tolerance)).
    def still_ok(limit: float) -> float:
        return (
            step + REACTION + (1.0 - (limit - MONITOR.speed_slack) / (limit * (1.0 + MONITOR.speed_tolerance))) / DECAY
        )

    times = [i * step for i in range(1, 200)]
    trips = [t for t in times if watch.base(t, V, 0.0, reduced) is not None]
    assert trips, "full speed long after the limit dropped must trip"
    first_over = min(t for t in times if t > still_ok(V))
    assert trips[0] == pytest.approx(first_over + (MONITOR.trip_after - 1) * step)
    # The arm's allowance holds and decays the same way.
    arm = monitor()
    full = {"panda_joint1": JOINT_SPEED}
    assert arm.joints(0.0, full, 1.0) is None
    trips = [t for t in times if arm.joints(t, full, reduced) is not None]
    first_over = min(t for t in times if t > still_ok(JOINT_SPEED))
    assert trips[0] == pytest.approx(first_over + (MONITOR.trip_after - 1) * step)


def test_the_first_scale_applies_at_once() -> None:
    # Nothing was allowed before it: a pause reported at start-up allows no speed at all.
    assert SpeedEnvelope(2.5, 0.3).update(5.0, 0.0) == 0.0
    envelope = SpeedEnvelope(2.5, 0.3)
    assert envelope.update(5.0, 0.4) == 0.4
    assert envelope.update(5.1, 0.0) == 0.4  # a later drop is held for the reaction time
