"""What safety watches while the robot runs: people nearby, measured motion, command rates.

Pure logic on plain numbers and timestamps (seconds on any monotonic clock); the node feeds it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

from shapely.affinity import rotate, translate
from shapely.geometry import Point, box
from shapely.geometry.base import BaseGeometry

from schemas.common import Pose2D
from schemas.safety import Rule
from services.safety.policyfile import HumanPolicy, MonitorPolicy


class RateLimit:
    """A token bucket: `rate` commands a second on average, bursts of `rate * burst_seconds`."""

    def __init__(self, rate: float, burst_seconds: float) -> None:
        self.rate = rate
        self.capacity = max(1.0, rate * burst_seconds)
        self._tokens = self.capacity
        self._at: float | None = None

    def allow(self, now: float) -> bool:
        if self._at is not None:
            self._tokens = min(self.capacity, self._tokens + (now - self._at) * self.rate)
        self._at = now
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


def footprint(pose: Pose2D, length: float, width: float) -> BaseGeometry:
    """The base's rectangle on the floor at `pose`."""
    shape = box(-length / 2, -width / 2, length / 2, width / 2)
    return translate(rotate(shape, pose.yaw, origin=(0, 0), use_radians=True), pose.x, pose.y)


def nearest_person(
    pose: Pose2D, size: tuple[float, float], hand: tuple[float, float] | None, people: Iterable[Person]
) -> tuple[float, Person] | None:
    """The nearest person and their distance from the base's footprint or the hand, whichever is nearer."""
    base = footprint(pose, *size)
    best: tuple[float, Person] | None = None
    for person in people:
        distance = base.distance(Point(person.x, person.y))
        if hand is not None:
            distance = min(distance, math.dist(hand, (person.x, person.y)))
        if best is None or distance < best[0]:
            best = (distance, person)
    return best


def separation(nearest: tuple[float, Person] | None, seen: bool, policy: HumanPolicy) -> Separation:
    """Speed and separation: full speed beyond D, reduced inside, paused inside d. People not
    reported recently (`seen` False) may be anywhere: reduced speed."""
    if not seen:
        return Separation(policy.reduced_speed_scale, "no recent report of where people are: reduced speed")
    if nearest is None:
        return Separation(1.0, "")
    distance, person = nearest
    if distance <= policy.stop_distance:
        why = f"{person.name} is {distance:.2f} m away, within {policy.stop_distance:g} m: paused"
        return Separation(0.0, why, distance, person.name)
    if distance <= policy.slow_distance:
        why = f"{person.name} is {distance:.2f} m away, within {policy.slow_distance:g} m: reduced speed"
        return Separation(policy.reduced_speed_scale, why, distance, person.name)
    return Separation(1.0, "", distance, person.name)


@dataclass(frozen=True)
class Trip:
    """A monitor's reason to trip the e-stop."""

    rule: Rule
    reason: str
    values: dict[str, float]


class SpeedEnvelope:
    """The speed allowed at each moment: the limit times the separation scale, except that after
    the scale drops the allowance falls at the deceleration limit (the robot needs time to slow)."""

    def __init__(self, decay_per_second: float) -> None:
        self.decay = decay_per_second
        self.scale = 1.0
        self._at: float | None = None

    def update(self, now: float, scale: float) -> float:
        if self._at is not None and scale < self.scale:
            self.scale = max(scale, self.scale - self.decay * (now - self._at))
        else:
            self.scale = scale
        self._at = now
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
        self._base_envelope = SpeedEnvelope(decay_per_second)
        self._arm_envelope = SpeedEnvelope(decay_per_second)
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
