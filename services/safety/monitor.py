"""What safety watches while the robot runs: people nearby, measured motion, command rates.

Pure logic on plain numbers and timestamps (seconds on any monotonic clock); the node feeds it.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from schemas.common import Pose2D
from schemas.safety import Rule
from services.footprint import distance_to_footprint
from services.safety.policyfile import HumanPolicy, MonitorPolicy


class RateLimit:
    """A token bucket: `rate` commands a second on average, bursts of `rate * burst_seconds`.
    Safe to call from several threads."""

    def __init__(self, rate: float, burst_seconds: float) -> None:
        self.rate = rate
        self.capacity = max(1.0, rate * burst_seconds)
        self._tokens = self.capacity
        self._at: float | None = None
        self._lock = threading.Lock()

    def allow(self, now: float) -> bool:
        with self._lock:
            if self._at is not None:
                self._tokens = min(self.capacity, self._tokens + max(0.0, now - self._at) * self.rate)
            self._at = now if self._at is None else max(self._at, now)
            if self._tokens >= 1.0:
                self._tokens -= 1.0
                return True
            return False


@dataclass(frozen=True)
class Person:
    name: str
    x: float
    y: float


@dataclass(frozen=True)
class Separation:
    """The speed allowed near people: `scale` of full speed, and why."""

    scale: float
    reason: str
    distance: float | None = None
    person: str | None = None


def nearest_person(
    pose: Pose2D,
    size: tuple[float, float],
    hand: tuple[float, float] | None,
    people: Iterable[Person],
    radius: float = 0.0,
    reach: float = 0.0,
) -> tuple[float, Person] | None:
    """The nearest person and the distance from the base's footprint or the hand, whichever is
    nearer, to their body (`radius` around where they stand; 0 when touching). A `hand` of None is
    one whose place is unknown: it may be anywhere within `reach` of the base's centre (the gate
    gives the arm's full reach, as navigation assumes). Asked at every heartbeat: the footprint's
    distance is measured without building a polygon."""
    best: tuple[float, Person] | None = None
    for person in people:
        distance = distance_to_footprint(pose.x, pose.y, pose.yaw, *size, (person.x, person.y))
        if hand is not None:
            distance = min(distance, math.dist(hand, (person.x, person.y)))
        else:
            distance = min(distance, math.dist((pose.x, pose.y), (person.x, person.y)) - reach)
        distance = max(0.0, distance - radius)
        if best is None or distance < best[0]:
            best = (distance, person)
    return best


# Reports and people kept for the window at most: every heartbeat measures the distance to each
# person kept (a few microseconds each), and it must stay well within the heartbeat's period. A
# household's cameras report a few people some tens of times a second.
MAX_PEOPLE_REPORTED = 4000


class PeopleReports:
    """Reports of where people are. Every report of the last `window` seconds counts, so a report
    with nobody in it cannot hide someone another recent report saw; none within it: unknown.

    At most `limit` entries (each report, and each person in it) are kept. A report beyond that (a
    flood, hostile or broken) is not kept, so anyone in it is nowhere counted: until it too is older
    than the window, `flooded` says so and the robot is paused."""

    def __init__(self, window: float, limit: int = MAX_PEOPLE_REPORTED) -> None:
        self.window = window
        self.limit = limit
        self._reports: deque[tuple[float, list[Person]]] = deque()
        self._kept = 0
        self._dropped_at: float | None = None
        self._lock = threading.Lock()

    def add(self, now: float, people: list[Person]) -> None:
        with self._lock:
            self._forget(now)
            if self._kept + 1 + len(people) > self.limit:
                self._dropped_at = now if self._dropped_at is None else max(self._dropped_at, now)
                return
            self._reports.append((now, people))
            self._kept += 1 + len(people)

    def _forget(self, now: float) -> None:
        while self._reports and now - self._reports[0][0] > self.window:
            _, people = self._reports.popleft()
            self._kept -= 1 + len(people)

    def flooded(self, now: float) -> bool:
        """Whether a report within the window was not kept (more than `limit` entries came in it)."""
        with self._lock:
            return self._dropped_at is not None and now - self._dropped_at <= self.window

    def people(self, now: float) -> list[Person] | None:
        """Everyone reported within the window, or None when nothing was reported in it."""
        with self._lock:
            self._forget(now)
            if not self._reports:
                return None
            return [person for _, people in self._reports for person in people]


def separation(
    nearest: tuple[float, Person] | None, seen: bool, policy: HumanPolicy, current: float = 1.0
) -> Separation:
    """Speed and separation: full speed beyond D, reduced inside, paused inside d. People not
    reported recently (`seen` False) may be anywhere: reduced speed.

    A stricter scale applies at once; a looser one only once the person is `release_margin` beyond
    the boundary (`current` is the scale in force), so a person standing at D does not flip the
    robot between two speeds with every report."""
    if not seen:
        return Separation(policy.reduced_speed_scale, "no recent report of where people are: reduced speed")
    if nearest is None:
        return Separation(1.0, "")
    distance, person = nearest
    stop_at = policy.stop_distance + (policy.release_margin if current <= 0.0 else 0.0)
    slow_at = policy.slow_distance + (policy.release_margin if current < 1.0 else 0.0)
    if distance <= stop_at:
        why = f"{person.name} is {distance:.2f} m away, within {stop_at:g} m: paused"
        return Separation(0.0, why, distance, person.name)
    if distance <= slow_at:
        why = f"{person.name} is {distance:.2f} m away, within {slow_at:g} m: reduced speed"
        return Separation(policy.reduced_speed_scale, why, distance, person.name)
    return Separation(1.0, "", distance, person.name)


@dataclass(frozen=True)
class Trip:
    """A monitor's reason to trip the e-stop."""

    rule: Rule
    reason: str
    values: dict[str, float]


@dataclass(frozen=True)
class _Drop:
    """One drop of the allowed speed: from `start`, held for the reaction time after `at`, then
    falling at the deceleration limit to `target`."""

    target: float
    start: float
    at: float

    def allowance(self, now: float, decay: float, reaction_time: float) -> float:
        return max(self.target, self.start - decay * max(0.0, now - self.at - reaction_time))


class SpeedEnvelope:
    """The speed allowed at each moment, as a fraction of the limit: the separation scale, except
    that after it drops the allowance holds for `reaction_time` (the robot hears of it and starts
    braking) and then falls at the deceleration limit (`decay_per_second` of full speed). A further
    drop during a fall starts its own hold without undoing the fall already under way. The first
    scale applies at once (nothing was allowed before it)."""

    def __init__(self, decay_per_second: float, reaction_time: float = 0.0) -> None:
        self.decay = decay_per_second
        self.reaction_time = reaction_time
        self.scale = 1.0
        self._drops: list[_Drop] = []
        self._started = False

    def _current(self, now: float) -> float:
        return min(d.allowance(now, self.decay, self.reaction_time) for d in self._drops)

    def update(self, now: float, scale: float) -> float:
        allowed = self._current(now) if self._drops else self.scale
        if not self._started or scale >= allowed:
            self._started = True
            self._drops = []
            self.scale = scale
            return scale
        if not self._drops or scale < self._drops[-1].target:
            self._drops.append(_Drop(scale, allowed, now))
        # Drops that have reached their target no longer limit anything a later one does not.
        self.scale = max(scale, self._current(now))
        return self.scale


class OverLimit:
    """True once a measurement has been over its limit `count` times in a row."""

    def __init__(self, count: int) -> None:
        self.count = count
        self._run = 0

    def update(self, over: bool) -> bool:
        self._run = self._run + 1 if over else 0
        return self._run >= self.count


class MotionMonitor:
    """Measured base and joint speeds against the limits (times the separation scale, with slack);
    over for `trip_after` samples in a row trips the e-stop."""

    def __init__(
        self,
        policy: MonitorPolicy,
        max_linear: float,
        max_angular: float,
        joint_velocity: dict[str, float],
        decay_per_second: float,
    ) -> None:
        self.policy = policy
        self.max_linear = max_linear
        self.max_angular = max_angular
        self.joint_velocity = joint_velocity
        self._base_envelope = SpeedEnvelope(decay_per_second, policy.reaction_time)
        self._arm_envelope = SpeedEnvelope(decay_per_second, policy.reaction_time)
        self._base_over = OverLimit(policy.trip_after)
        self._arm_over = OverLimit(policy.trip_after)

    def _allowed(self, limit: float, scale: float) -> float:
        return limit * scale * (1.0 + self.policy.speed_tolerance) + self.policy.speed_slack

    def base(self, now: float, linear: float, angular: float, scale: float) -> Trip | None:
        scale = self._base_envelope.update(now, scale)
        v_allowed, w_allowed = self._allowed(self.max_linear, scale), self._allowed(self.max_angular, scale)
        over = abs(linear) > v_allowed or abs(angular) > w_allowed
        if not self._base_over.update(over):
            return None
        return Trip(
            Rule.MONITOR_SPEED,
            f"the base was measured at {abs(linear):.2f} m/s, {abs(angular):.2f} rad/s; "
            f"allowed {v_allowed:.2f} m/s, {w_allowed:.2f} rad/s",
            {"speed_mps": linear, "turn_rps": angular, "allowed_mps": v_allowed, "allowed_rps": w_allowed},
        )

    def joints(self, now: float, velocities: dict[str, float], scale: float) -> Trip | None:
        scale = self._arm_envelope.update(now, scale)
        worst: tuple[float, str, float, float] | None = None
        for name, velocity in velocities.items():
            limit = self.joint_velocity.get(name)
            if limit is None:
                continue
            allowed = self._allowed(limit, scale)
            ratio = abs(velocity) / allowed
            if ratio > 1.0 and (worst is None or ratio > worst[0]):
                worst = (ratio, name, velocity, allowed)
        if not self._arm_over.update(worst is not None) or worst is None:
            return None
        _, name, velocity, allowed = worst
        return Trip(
            Rule.MONITOR_JOINT_SPEED,
            f"{name} was measured at {abs(velocity):.2f} rad/s; allowed {allowed:.2f} rad/s",
            {"speed_rps": velocity, "allowed_rps": allowed},
        )
