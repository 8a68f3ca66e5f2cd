"""Shared control's teleop filter, pure: the person's twist, slowed and steered so the footprint keeps off obstacles.

The person sets the direction; the filter does the fine motion, in two parts:

- `shape`: the commanded velocity, as a vector on the floor, loses part of its component into each
  obstacle within SLOW_DISTANCE of the footprint, all of it at STOP_DISTANCE (the projection of
  Nav2's collision monitor and MoveIt Servo, graded by distance like their slowdown zones). Driving
  straight at a wall the base slows to a stop; at an angle the vector left points along the wall,
  and the base (a differential drive) is steered towards it, so it slides along instead of stopping
  dead; within HEAD_ON of head-on it only slows. Motion away from or along an obstacle keeps its
  full speed. Near people every speed is multiplied by safety's separation scale.
- `guard`: the hard rule, on the twist actually sent: held for the horizon and then braked, the
  footprint comes no closer than STOP_DISTANCE to a wall, furniture or person, and the base's disc
  no closer to a keep-out zone (as the policy grows zones), or no closer than it already is. A
  footprint already touching or overlapping something (odometry drift, a bump) is 0 away however
  deep it is: for that thing the rule is that the overlap never grows (backing off, or sliding
  along without going deeper, passes; further in does not). Otherwise the forward speed is cut
  (bisected) until it holds; a turn in place is allowed unless the footprint would come within
  TOUCH_DISTANCE. The forward speed is only ever cut, never raised or reversed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import msgspec
import numpy as np
import shapely
from shapely.geometry import Point
from shapely.geometry.base import BaseGeometry
from shapely.ops import nearest_points

from schemas.common import Pose2D
from schemas.robot import Twist
from services.footprint import TURN_STEP

# The footprint keeps this far (m) from walls, furniture and people while driving; motion into an
# obstacle this close is removed entirely.
STOP_DISTANCE = 0.05
# Beyond this (m) an obstacle does not slow the base; between the two, the part of the velocity
# into it is cut in proportion.
SLOW_DISTANCE = 0.5
# A turn in place may bring the footprint this close (m), not closer (odometry is not exact).
TOUCH_DISTANCE = 0.01
# Meeting an obstacle within this angle of head-on, the base slows straight on instead of turning
# along it: a person driving at a wall, a few degrees off, means to stop there, not to turn away.
HEAD_ON = math.radians(20.0)
# How hard (rad/s per radian between heading and the deflected direction) the base is steered to
# slide along an obstacle.
STEER_GAIN = 2.0
# The predicted path is checked every this many metres of travel (and every TURN_STEP of turn).
PATH_STEP = 0.02
# Bisections of the forward speed in `guard`: the speed kept is within 1/2^n of the largest clear one.
BISECTIONS = 8
# Speeds (m/s, rad/s) below this count as zero; distances equal within it count as equal.
STILL = 1e-6
EPSILON = 1e-6
# Overlaps (m^2) equal within this count as equal (the robot rules' TOUCHING).
AREA_EPSILON = 1e-6


@dataclass(frozen=True)
class SharedLimits:
    """What the filter assumes of the base: a twist is held `horizon` seconds (the policy's
    cmd_vel_horizon), then braked at `braking` m/s^2; the steering turns at most `max_angular` rad/s."""

    horizon: float
    braking: float
    max_angular: float
    length: float
    width: float
    radius: float  # the base's half-diagonal (plus the policy's margin): zones keep this far from its centre
    stop_distance: float = STOP_DISTANCE
    slow_distance: float = SLOW_DISTANCE


@dataclass(frozen=True)
class Surroundings:
    """What the base must keep off, by name: `obstacles` (walls, furniture, people) are kept from
    the footprint, `zones` (keep-out zones, not grown) from the disc of the base's `radius`."""

    obstacles: Sequence[tuple[str, BaseGeometry]] = ()
    zones: Sequence[tuple[str, BaseGeometry]] = ()


@dataclass(frozen=True)
class Filtered:
    """The twist the filter lets through, whether it `slowed` or `deflected` it, the nearest thing
    (`nearest`, `clearance` in metres; None and inf when nothing is near), and why."""

    twist: Twist
    slowed: bool = False
    deflected: bool = False
    nearest: str | None = None
    clearance: float = math.inf
    note: str = ""
    values: dict[str, float] = field(default_factory=dict)

    @property
    def changed(self) -> bool:
        return self.slowed or self.deflected


@dataclass(frozen=True)
class _Near:
    name: str
    distance: float
    normal: tuple[float, float] | None  # unit vector from the obstacle towards the base; None if unknown


def _footprints(xs: np.ndarray, ys: np.ndarray, yaws: np.ndarray, length: float, width: float) -> np.ndarray:
    """The footprint's corners at each pose: shape (n, 4, 2)."""
    a = np.array([length / 2, -length / 2, -length / 2, length / 2])
    b = np.array([width / 2, width / 2, -width / 2, -width / 2])
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    return np.stack([xs[:, None] + c * a - s * b, ys[:, None] + s * a + c * b], axis=-1)


def predict(pose: Pose2D, twist: Twist, limits: SharedLimits) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The poses (x, y, yaw arrays, the first one `pose`) the base passes holding `twist` for the
    horizon and then braking; the braking is counted as the same twist held for the time it covers
    the braking distance at full speed."""
    v, w = twist.linear_x, twist.angular_z
    duration = limits.horizon + abs(v) / (2 * limits.braking)
    travel, turn = abs(v) * duration, abs(w) * duration
    count = max(1, math.ceil(travel / PATH_STEP), math.ceil(turn / TURN_STEP))
    t = np.linspace(0.0, duration, count + 1)
    yaws = pose.yaw + w * t
    if abs(w) < STILL:
        xs = pose.x + v * t * math.cos(pose.yaw)
        ys = pose.y + v * t * math.sin(pose.yaw)
    else:
        xs = pose.x + v / w * (np.sin(yaws) - math.sin(pose.yaw))
        ys = pose.y - v / w * (np.cos(yaws) - math.cos(pose.yaw))
    return xs, ys, yaws


class SharedFilter:
    """The filter over fixed `limits`; each call gets the pose and what surrounds the base now."""

    def __init__(self, limits: SharedLimits) -> None:
        self.limits = limits

    # Where things are

    def _body(self, pose: Pose2D) -> shapely.Polygon:
        """The footprint at `pose`."""
        lim = self.limits
        return shapely.Polygon(
            _footprints(np.array([pose.x]), np.array([pose.y]), np.array([pose.yaw]), lim.length, lim.width)[0]
        )

    def _near(self, pose: Pose2D, around: Surroundings) -> list[_Near]:
        """Every obstacle and zone, nearest first: how far from the base, and which way it pushes."""
        lim = self.limits
        body = self._body(pose)
        centre = Point(pose.x, pose.y)
        found = []
        for name, shape in around.obstacles:
            found.append(_Near(name, body.distance(shape), _normal(body, shape)))
        for name, shape in around.zones:
            found.append(_Near(name, centre.distance(shape) - lim.radius, _normal(centre, shape)))
        return sorted(found, key=lambda n: n.distance)

    def clearance(self, xs: np.ndarray, ys: np.ndarray, yaws: np.ndarray, around: Surroundings) -> np.ndarray:
        """At each step between consecutive poses (or at the one pose), the least distance from the
        base to anything around it: the footprint's sweep to obstacles, the disc's to zones."""
        lim = self.limits
        corners = _footprints(xs, ys, yaws, lim.length, lim.width)
        if len(xs) > 1:
            # The sweep of each step: the hull of the footprint at both ends (exact driving straight;
            # turning, a step is at most TURN_STEP and the corners' arc within a millimetre of it).
            pairs = np.concatenate([corners[:-1], corners[1:]], axis=1)
            swept = shapely.convex_hull(shapely.multipoints(pairs))
            centres = shapely.linestrings(
                np.stack([np.stack([xs[:-1], ys[:-1]], -1), np.stack([xs[1:], ys[1:]], -1)], 1)
            )
        else:
            swept = shapely.polygons(corners)
            centres = shapely.points(np.stack([xs, ys], -1))
        least = np.full(len(swept), math.inf)
        for _, shape in around.obstacles:
            least = np.minimum(least, shapely.distance(swept, shape))
        for _, shape in around.zones:
            least = np.minimum(least, shapely.distance(centres, shape) - lim.radius)
        return least

    def _clear(
        self, pose: Pose2D, twist: Twist, around: Surroundings, now: float, touched: Sequence[BaseGeometry] = ()
    ) -> bool:
        """Whether holding `twist` (then braking) keeps the base as far off everything as it must:
        `around` as far as the rule says (`now`: the nearest of them now), and no deeper into any of
        `touched` (obstacles the footprint touches or overlaps now) than it already is."""
        if abs(twist.linear_x) < STILL and abs(twist.angular_z) < STILL:
            return True
        keep = self.limits.stop_distance if abs(twist.linear_x) >= STILL else TOUCH_DISTANCE
        required = min(keep, now) - EPSILON
        path = predict(pose, twist, self.limits)
        if not np.all(self.clearance(*path, around) >= required):
            return False
        if touched:
            prints = shapely.polygons(_footprints(*path, self.limits.length, self.limits.width))
            for shape in touched:
                overlap = shapely.area(shapely.intersection(prints, shape))
                if np.any(overlap > overlap[0] + AREA_EPSILON):
                    return False
        return True

    # The two parts

    def shape(self, twist: Twist, pose: Pose2D, around: Surroundings, people_scale: float = 1.0) -> Filtered:
        """The person's twist slowed near people (`people_scale`) and, near an obstacle, with the part
        into it cut and the base steered along it (see the module's docstring). Not yet guarded."""
        lim = self.limits
        scale = max(0.0, min(1.0, people_scale))
        v, w = twist.linear_x * scale, twist.angular_z * scale
        near = self._near(pose, around)
        nearest = near[0] if near else None
        values: dict[str, float] = {"shared_requested_mps": twist.linear_x, "shared_requested_rps": twist.angular_z}
        if nearest is not None:
            values["shared_clearance_m"] = max(nearest.distance, 0.0)
        slowed = scale < 1.0 and (twist.linear_x != 0.0 or twist.angular_z != 0.0)
        notes = [f"a person is near: speed x{scale:.2f}"] if slowed else []
        if abs(v) < STILL:
            return self._result(twist, v, w, slowed, False, nearest, notes, values)
        # The velocity on the floor, as a unit direction `u` (the way the base drives) and a speed.
        heading = -1.0 if v < 0 else 1.0
        u = np.array([math.cos(pose.yaw), math.sin(pose.yaw)]) * heading
        wanted = u * abs(v)
        span = lim.slow_distance - lim.stop_distance
        for item in near:
            if item.distance >= lim.slow_distance or item.normal is None:
                continue
            into = float(wanted @ np.array(item.normal))
            if into >= 0.0:
                continue  # moving away from it or along it
            cut = 1.0 - min(max((item.distance - lim.stop_distance) / span, 0.0), 1.0)
            if -into >= math.cos(HEAD_ON) * float(np.hypot(*wanted)):
                wanted = wanted * (1.0 - cut)  # head-on: slower, same direction
            else:
                wanted = wanted - cut * into * np.array(item.normal)
        along = float(wanted @ u)
        if along <= STILL:
            # Nothing of the command's direction is left (the projection turned it back): stop.
            return self._result(twist, 0.0, w, True, False, nearest, [*notes, "blocked ahead"], values)
        speed = float(np.hypot(*wanted))
        angle = math.atan2(u[0] * wanted[1] - u[1] * wanted[0], along)  # from `u` to the deflected direction
        deflected = abs(angle) > 1e-3
        steer = STEER_GAIN * angle if deflected else 0.0
        w_max = lim.max_angular * scale
        w_new = max(-w_max, min(w_max, w + steer)) if deflected else w
        v_new = heading * min(along, abs(v))
        if speed < abs(v) - EPSILON:
            slowed = True
            notes.append(f"slowed from {abs(v):.2f} to {abs(v_new):.2f} m/s")
        if deflected:
            notes.append(f"steered {w_new - w:+.2f} rad/s to slide along it")
            values["shared_steer_rps"] = w_new - w
        return self._result(twist, v_new, w_new, slowed, deflected, nearest, notes, values)

    def guard(self, twist: Twist, pose: Pose2D, around: Surroundings) -> Filtered:
        """`twist`, or the fastest forward speed in the same direction (keeping its turn) that holds
        the rule in the module's docstring; a turn in place that would touch is dropped as well."""
        near = self._near(pose, around)
        nearest = near[0] if near else None
        # What the footprint touches or overlaps now is held to its overlap; the rest to the distance rule.
        body = self._body(pose)
        touched = [shape for _, shape in around.obstacles if body.distance(shape) <= EPSILON]
        if touched:
            apart = [(name, shape) for name, shape in around.obstacles if body.distance(shape) > EPSILON]
            around = Surroundings(apart, around.zones)
            now = min((n.distance for n in self._near(pose, around)), default=math.inf)
        else:
            now = nearest.distance if nearest is not None else math.inf
        v, w = twist.linear_x, twist.angular_z

        def clear(linear: float, turn: float) -> bool:
            return self._clear(
                pose, msgspec.structs.replace(twist, linear_x=linear, angular_z=turn), around, now, touched
            )

        if clear(v, w):
            return self._result(twist, v, w, False, False, nearest, [], {})
        for turn in (w, 0.0):
            if not clear(0.0, turn):
                continue
            low, high = 0.0, 1.0
            for _ in range(BISECTIONS):
                mid = (low + high) / 2
                if clear(v * mid, turn):
                    low = mid
                else:
                    high = mid
            where = f"{max(now, 0.0) * 100:.1f} cm from {nearest.name}" if nearest else "near an obstacle"
            why = f"cut to {abs(v * low):.2f} m/s" + ("" if turn == w else ", turn dropped") + f": {where}"
            return self._result(twist, v * low, turn, True, False, nearest, [why], {})
        return self._result(twist, 0.0, 0.0, True, False, nearest, ["stopped: even turning would touch"], {})

    def filter(self, twist: Twist, pose: Pose2D, around: Surroundings, people_scale: float = 1.0) -> Filtered:
        """`shape` then `guard`: what shared control sends when nothing else limits the twist."""
        shaped = self.shape(twist, pose, around, people_scale)
        return combine(shaped, self.guard(shaped.twist, pose, around))

    def _result(
        self,
        asked: Twist,
        v: float,
        w: float,
        slowed: bool,
        deflected: bool,
        nearest: _Near | None,
        notes: list[str],
        values: dict[str, float],
    ) -> Filtered:
        out = msgspec.structs.replace(asked, linear_x=v, angular_z=w)
        values = {**values, "shared_speed_mps": v, "shared_turn_rps": w}
        if slowed or deflected:
            values["shared"] = 1.0
        where = f" ({nearest.name} {max(nearest.distance, 0.0) * 100:.1f} cm away)" if nearest and notes else ""
        note = ("shared: " + "; ".join(notes) + where) if notes else ""
        name, distance = (nearest.name, nearest.distance) if nearest else (None, math.inf)
        return Filtered(out, slowed, deflected, name, distance, note, values)


def combine(first: Filtered, then: Filtered) -> Filtered:
    """Two passes of the filter as one: the second's twist, either's reasons."""
    notes = "; ".join(n.removeprefix("shared: ") for n in (first.note, then.note) if n)
    values = {**first.values, **then.values}
    values.update({k: v for k, v in first.values.items() if k.startswith("shared_requested")})
    if first.changed or then.changed:
        values["shared"] = 1.0
    return Filtered(
        then.twist,
        first.slowed or then.slowed,
        first.deflected or then.deflected,
        then.nearest,
        then.clearance,
        f"shared: {notes}" if notes else "",
        values,
    )


def _normal(body: BaseGeometry, shape: BaseGeometry) -> tuple[float, float] | None:
    """The unit vector from `shape`'s nearest point towards `body`; touching or overlapping, from
    that point towards the body's centre. None when it cannot be told."""
    ours, theirs = nearest_points(body, shape)
    dx, dy = ours.x - theirs.x, ours.y - theirs.y
    if math.hypot(dx, dy) < EPSILON:
        centre = body.centroid
        dx, dy = centre.x - theirs.x, centre.y - theirs.y
    length = math.hypot(dx, dy)
    return None if length < EPSILON else (dx / length, dy / length)
