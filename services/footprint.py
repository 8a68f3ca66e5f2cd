"""The base on the floor plan: the rectangle it covers at a pose, and what it sweeps driving a route.

The sim drives a route leg by leg (`route_legs`): it turns in place to face the next point and
drives straight to it (a turn of MIN_TURN or less is not drawn, and the leg is drawn facing as the
base does); a short leg behind it (at most MAX_REVERSE) it drives backwards instead of turning
round. At the last point it turns to the goal's heading. It keeps its footprint within
TRACKING_TOLERANCE of what those legs sweep, and aborts the goal otherwise. The sim, the executor's
base planner and safety all take the legs, the sweeps and the clearance rule from here, so the
route the planner found clear is the one safety checks and the one the sim drives. Pure logic.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry

from schemas.common import Pose2D

# A turn in place is drawn as the footprint every this many radians; between two samples the
# corners of a 0.6 x 0.5 m base cut inside the arc by under half a millimetre.
TURN_STEP = math.radians(5.0)
# Turns and legs shorter than these are not drawn (the sim does not move for them either).
MIN_TURN = 1e-3
MIN_LEG = 1e-4
# A leg at most this long that starts more than a quarter turn from the base's heading is driven
# backwards: how the base leaves a spot it parked at close to furniture, too close to turn round.
# Shorter than worldmodel.PRE_GOAL_DISTANCE, so the last straight-in leg is always driven forwards.
MAX_REVERSE = 0.35
# How far (metres) the sim lets its footprint stray from the route's sweeps before it aborts the
# goal: the centre off the leg plus the corners turned off the leg's heading. Safety keeps every
# sweep this far from walls and furniture, so the footprint as driven never touches them.
TRACKING_TOLERANCE = 0.03
# Distances equal up to this count as equal (a leg straight away from furniture keeps its distance).
EPSILON = 1e-9
# Overlaps of the footprint with something it touches at the start count as grown beyond this (m^2:
# a square millimetre; m for an outline that is a line): backing straight off an overlap 2 cm deep
# along a heading 1 mrad off the base's (a start read a hair off) covers 0.2 mm^2 more of it.
OVERLAP_EPSILON = 1e-6


def footprint(x: float, y: float, yaw: float, length: float, width: float, margin: float = 0.0) -> Polygon:
    """The rectangle the base covers at (x, y, yaw): `length` along its heading, `width` across,
    grown by `margin` on every side."""
    # shapely.polygons: the same polygon as Polygon(...), in two thirds of the time (the planner makes
    # one for every motion it considers).
    shape: Polygon = shapely.polygons(_corners(x, y, yaw, length, width, margin))
    return shape


def _corners(x: float, y: float, yaw: float, length: float, width: float, margin: float) -> list[tuple[float, float]]:
    half_l, half_w = length / 2 + margin, width / 2 + margin
    c, s = math.cos(yaw), math.sin(yaw)
    corners = [(half_l, half_w), (-half_l, half_w), (-half_l, -half_w), (half_l, -half_w)]
    return [(x + c * a - s * b, y + s * a + c * b) for a, b in corners]


def distance_to_footprint(
    x: float, y: float, yaw: float, length: float, width: float, point: tuple[float, float]
) -> float:
    """How far `point` is from `footprint(x, y, yaw, length, width)`, 0 inside it: the same as
    shapely's distance, without building the polygon (the sim asks it many times a second)."""
    dx, dy = point[0] - x, point[1] - y
    c, s = math.cos(yaw), math.sin(yaw)
    along, across = abs(c * dx + s * dy) - length / 2, abs(-s * dx + c * dy) - width / 2
    return math.hypot(max(along, 0.0), max(across, 0.0))


def turn_angle(yaw_from: float, yaw_to: float) -> float:
    """The signed shortest turn from one heading to another, as the sim turns."""
    return math.remainder(yaw_to - yaw_from, math.tau)


def leg_heading(yaw: float, here: tuple[float, float], point: tuple[float, float]) -> tuple[float, bool]:
    """The heading the base holds driving from `here` to `point` when it now faces `yaw`, and
    whether it drives that leg backwards."""
    heading = math.atan2(point[1] - here[1], point[0] - here[0])
    if math.dist(here, point) <= MAX_REVERSE and abs(turn_angle(yaw, heading)) > math.pi / 2:
        return math.remainder(heading + math.pi, math.tau), True
    return heading, False


@dataclass(frozen=True)
class Leg:
    """One straight leg of a route: the base turns at `start` to `heading`, then drives to `end`
    holding it (backwards when `backwards`: `heading` then points away from `end`)."""

    start: tuple[float, float]
    end: tuple[float, float]
    heading: float
    backwards: bool

    @property
    def length(self) -> float:
        return math.dist(self.start, self.end)


def route_legs(start: Pose2D, points: Sequence[tuple[float, float]]) -> list[Leg]:
    """The legs of driving from `start` through `points` (see worldmodel.drive_route), in order."""
    legs: list[Leg] = []
    here, yaw = (start.x, start.y), start.yaw
    for point in points:
        if math.dist(here, point) < MIN_LEG:
            continue
        heading, backwards = leg_heading(yaw, here, point)
        legs.append(Leg(here, (float(point[0]), float(point[1])), heading, backwards))
        here, yaw = legs[-1].end, heading
    return legs


@dataclass(frozen=True)
class Sweep:
    """One piece of a route: the floor the base covers while doing `what`, ending at (x, y); `parts`
    cover it together (a turn's footprints, turn_footprints; a leg's drive_sweep alone)."""

    what: str
    parts: tuple[Polygon, ...]
    x: float
    y: float

    @cached_property
    def bounds(self) -> tuple[float, float, float, float]:
        """The box around it: (min x, min y, max x, max y)."""
        low_x, low_y, high_x, high_y = shapely.total_bounds(_array(self.parts))
        return float(low_x), float(low_y), float(high_x), float(high_y)

    @cached_property
    def shape(self) -> Polygon:
        """The floor covered, as one polygon: the union of `parts`, made when first asked for (a
        turn's union costs more than every check on the parts; clearance_problem needs none)."""
        shape: Polygon = self.parts[0] if len(self.parts) == 1 else shapely.union_all(self.parts)
        return shape


def turn_footprints(
    x: float, y: float, yaw_from: float, yaw_to: float, length: float, width: float, margin: float
) -> NDArray[np.object_]:
    """The footprints a turn in place at (x, y) from `yaw_from` to `yaw_to` the short way is drawn
    as, one every TURN_STEP at most, both ends included; made in one call (each the same polygon
    footprint() makes)."""
    angle = turn_angle(yaw_from, yaw_to)
    count = max(1, math.ceil(abs(angle) / TURN_STEP))
    rings = [_corners(x, y, yaw_from + angle * k / count, length, width, margin) for k in range(count + 1)]
    return shapely.polygons(np.array(rings))


def drive_sweep(
    a: tuple[float, float], b: tuple[float, float], yaw: float, length: float, width: float, margin: float
) -> Polygon:
    """The floor covered driving straight from `a` to `b` facing `yaw` (the leg's own heading)."""
    start = footprint(a[0], a[1], yaw, length, width, margin)
    end = footprint(b[0], b[1], yaw, length, width, margin)
    return start.union(end).convex_hull


def _at(point: tuple[float, float]) -> str:
    return f"({point[0]:.2f}, {point[1]:.2f})"


def route_sweeps(
    start: Pose2D,
    points: Sequence[tuple[float, float]],
    final_yaw: float,
    length: float,
    width: float,
    margin: float = 0.0,
) -> list[Sweep]:
    """The pieces of driving from `start` through `points` (see worldmodel.drive_route) and turning
    to `final_yaw` at the last one, in the order the sim drives them (route_legs)."""
    sweeps: list[Sweep] = []
    yaw = start.yaw
    here = (start.x, start.y)
    for leg in route_legs(start, points):
        if abs(turn_angle(yaw, leg.heading)) > MIN_TURN:
            parts = tuple(turn_footprints(leg.start[0], leg.start[1], yaw, leg.heading, length, width, margin))
            sweeps.append(Sweep(f"turning at {_at(leg.start)}", parts, leg.start[0], leg.start[1]))
            yaw = leg.heading
        # A leg that needs no turn is drawn facing as the base does: the first then begins with exactly
        # the start's footprint. Drawn at its own heading, a hair off a start read a moment after the
        # route was planned, a leg straight out of a tight spot came closer than the start (by 25 um).
        shape = drive_sweep(leg.start, leg.end, yaw, length, width, margin)
        verb = "backing" if leg.backwards else "driving"
        sweeps.append(Sweep(f"{verb} from {_at(leg.start)} to {_at(leg.end)}", (shape,), leg.end[0], leg.end[1]))
        here = leg.end
    if abs(turn_angle(yaw, final_yaw)) > MIN_TURN:
        parts = tuple(turn_footprints(here[0], here[1], yaw, final_yaw, length, width, margin))
        sweeps.append(Sweep(f"turning at {_at(here)}", parts, here[0], here[1]))
    return sweeps


def _cm(metres: float) -> str:
    return f"{round(max(metres, 0.0) * 100, 1):g} cm"


def nearest(shape: BaseGeometry, obstacles: Sequence[tuple[str, BaseGeometry]]) -> tuple[str, float]:
    """The name of the obstacle nearest `shape`, and how far it is (0 touching or inside)."""
    return nearest_to_parts((shape,), obstacles)


def nearest_to_parts(parts: Sequence[BaseGeometry], obstacles: Sequence[tuple[str, BaseGeometry]]) -> tuple[str, float]:
    """nearest() for the union of `parts` without making it: every part's distance to every
    obstacle in one call, the least of them (the first obstacle of the least, as min() gives). An
    empty outline (a wall of no length) is infinitely far, not NaN away, and so is nothing at all (a
    world without walls or furniture)."""
    if not obstacles:
        return "nothing", math.inf
    outlines = _array([outline for _, outline in obstacles])
    distances = _distances(parts, outlines, shapely.is_empty(outlines))
    best = int(np.argmin(distances))
    return obstacles[best][0], float(distances[best])


def _distances(
    parts: Sequence[BaseGeometry], outlines: NDArray[np.object_], empty: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """Each of `outlines`' distance to the nearest of `parts`, in one call; infinite for an `empty`
    one (a wall of no length), not NaN."""
    distances: NDArray[np.float64] = shapely.distance(_array(parts)[:, np.newaxis], outlines).min(axis=0)
    distances[empty] = np.inf
    return distances


def _array(geometries: Sequence[BaseGeometry]) -> NDArray[np.object_]:
    """Geometries as a flat array of them, for shapely's functions that take many at once."""
    array = np.empty(len(geometries), dtype=object)
    array[:] = geometries
    return array


def clearance_problem(
    start: Pose2D,
    sweeps: Sequence[Sweep],
    obstacles: Sequence[tuple[str, BaseGeometry]],
    margin: float,
    length: float,
    width: float,
) -> tuple[Sweep, str] | None:
    """The first of a route's `sweeps` (route_sweeps at margin 0) that comes within `margin` of one
    of the named `obstacles` ("the kitchen counter", its outline), with why; None when every one
    keeps clear. Leaving the start (until the base first stands somewhere else) the footprint may
    stay as close to each obstacle as it already is there, never closer: a base parked near
    furniture can leave. One it already touches or overlaps (odometry's drift, a bump), 0 away however
    deep, it may not overlap more (by area): backing off or sliding along passes, further in does not.
    Every other obstacle keeps the margin from the first sweep on."""
    if not obstacles:
        return None
    outlines = _array([outline for _, outline in obstacles])
    empty = shapely.is_empty(outlines)
    at_start = footprint(start.x, start.y, start.yaw, length, width)
    from_start = _distances((at_start,), outlines, empty)
    leaving_required = np.minimum(margin, from_start)
    touching = np.flatnonzero(from_start <= EPSILON)
    overlaps = _overlaps(at_start, outlines[touching]) if touching.size else None
    leaving = True
    for sweep in sweeps:
        distances = _distances(sweep.parts, outlines, empty)
        required = leaving_required if leaving else margin
        if leaving and overlaps is not None:
            deeper = _deeper(at_start, sweep, outlines[touching], overlaps)
            if deeper is not None:
                return sweep, f"{sweep.what} the base would go further into {obstacles[int(touching[deeper])][0]}"
        was_leaving, leaving = leaving, leaving and (sweep.x, sweep.y) == (start.x, start.y)
        short = np.flatnonzero(distances < required - EPSILON)
        if was_leaving:  # one the start touches: the overlap's area tells, above
            short = short[from_start[short] > EPSILON]
        if not short.size:
            continue
        k = int(short[np.argmin(distances[short])])  # the first of the nearest, as min() gives
        name, distance = obstacles[k][0], float(distances[k])
        if distance <= 0.0:
            return sweep, f"{sweep.what} the base would hit {name}"
        if was_leaving and from_start[k] < margin:
            return sweep, f"{sweep.what} the base would come {_cm(distance)} from {name}, closer than it starts"
        return sweep, f"{sweep.what} the base would come {_cm(distance)} from {name} (it keeps {_cm(margin)})"
    return None


def _overlaps(shape: BaseGeometry, touched: NDArray[np.object_]) -> NDArray[np.float64]:
    """How much of each of the `touched` outlines `shape` covers: its area, or for an outline with
    none (a wall drawn as a line) its length."""
    common = shapely.intersection(shape, touched)
    return np.where(shapely.get_dimensions(touched) == 2, shapely.area(common), shapely.length(common))


def _deeper(at_start: Polygon, sweep: Sweep, touched: NDArray[np.object_], overlaps: NDArray[np.float64]) -> int | None:
    """The index of the first of the `touched` outlines that the start's footprint and `sweep`
    together cover more of (beyond OVERLAP_EPSILON) than the start did (`overlaps`), or None. With the
    start: a sweep after a turn begins elsewhere, and could give up one part of the overlap to enter
    another."""
    covered = shapely.union_all(_array([at_start, *sweep.parts]))
    grown = np.flatnonzero(_overlaps(covered, touched) > overlaps + OVERLAP_EPSILON)
    return int(grown[0]) if grown.size else None
