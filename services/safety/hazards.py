"""Known hazards: safety's memory of incidents in words, and where it makes the robot more careful.

Pure: the caution zone a pose or a route is in (ZoneMap: the zones with a grid index, so a lookup
looks only at the zones nearby), the places a plan sends the base and the hand, the plan check's
warnings about earlier incidents there, and the lines a planner's prompt or an agent's scene shows.
Nothing here can loosen a limit: a zone only ever lowers a speed (to the policy's scale or lower).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

import msgspec

from schemas.common import fmt_point
from schemas.incidents import CautionZone, Incident, IncidentKind
from schemas.plan import GroundedPlan, GroundedStep, NavigateStep, PickStep, PlaceStep, fallback_labels, step_labels

# A plan check lists at most this many warnings (the last one says how many more there were).
MAX_WARNINGS = 5
# A plan check looks up at most this many earlier incidents near its places (the newest).
NEAR_LIMIT = 20

KIND_WORDS = {
    IncidentKind.ESTOP: "e-stop",
    IncidentKind.MONITOR: "monitor trip",
    IncidentKind.WATCHDOG: "watchdog stop",
    IncidentKind.VETO: "vetoed command",
    IncidentKind.NEAR_MISS: "near-miss",
    IncidentKind.GRASP_FAILED: "failed grasp",
    IncidentKind.DROPPED: "dropped object",
    IncidentKind.COLLISION: "collision",
}


def ago(stamp: float, now: float) -> str:
    """How long ago `stamp` was, in the unit a person would use ("5 s ago", "2 days ago")."""
    seconds = max(0.0, now - stamp)
    if seconds < 60:
        return f"{int(seconds)} s ago"
    unit, size = next((u, s) for u, s in (("day", 86400), ("hour", 3600), ("minute", 60)) if seconds >= s)
    n = int(seconds // size)
    return f"{n} {unit}{'' if n == 1 else 's'} ago"


def why(incident: Incident) -> str:
    """Who triggered it and why, as far as the store knows: "operator: person in the way"."""
    parts = [p for p in (incident.source, incident.reason.strip()) if p]
    return ": ".join(parts)


def incident_line(incident: Incident, now: float) -> str:
    """One incident for a person or a model: "e-stop at (2.10, 3.00) 2 days ago (operator: person in
    the way)"."""
    where = (
        " (where unknown)" if incident.x is None or incident.y is None else f" at {fmt_point(incident.x, incident.y)}"
    )
    reason = f" ({why(incident)})" if why(incident) else ""
    cleared = "; its caution zone was cleared" if incident.cleared else ""
    return f"{KIND_WORDS[incident.kind]}{where} {ago(incident.stamp, now)}{reason}{cleared} [incident {incident.id}]"


def zone_summary(zone: CautionZone) -> str:
    """ "3 incidents within 1.0 m of (2.10, 3.00) (near_miss, estop)"."""
    kinds = f" ({', '.join(zone.kinds)})" if zone.kinds else ""
    plural = "" if zone.count == 1 else "s"
    return f"{zone.count} incident{plural} within {zone.radius:g} m of {fmt_point(zone.x, zone.y)}{kinds}"


def clear_hint(zone: CautionZone) -> str:
    some = zone.incidents[0] if zone.incidents else "ID"
    return f"an operator clears it with `tether incidents clear {some} --reason ...`"


def zone_reason(zone: CautionZone) -> str:
    """Why the heartbeat's speed is lower: the zone the base is in, and who may clear it."""
    return f"caution zone: {zone_summary(zone)}: {zone.speed_scale:.0%} of the speed limits; {clear_hint(zone)}"


def zone_line(zone: CautionZone) -> str:
    """One caution zone for a person or a model."""
    return (
        f"caution zone: {zone_summary(zone)}: the robot keeps to {zone.speed_scale:.0%} of its speed limits "
        f"within {zone.radius:g} m of {fmt_point(zone.x, zone.y)} until an operator clears it"
    )


# Where a zone applies

# A zone whose reach spans more grid cells than this (a huge radius) is looked at by every lookup.
MAX_ZONE_CELLS = 256
# The smallest grid cell (m), whatever the radius.
MIN_CELL = 0.05

Cell = tuple[int, int]


def _span(x0: float, y0: float, x1: float, y1: float, cell: float) -> tuple[range, range]:
    """The cells a box (x0, y0)-(x1, y1) overlaps, as column and row ranges."""
    return (
        range(math.floor(x0 / cell), math.floor(x1 / cell) + 1),
        range(math.floor(y0 / cell), math.floor(y1 / cell) + 1),
    )


def _leg_cells(a: tuple[float, float], b: tuple[float, float], margin: float, cell: float) -> Iterator[Cell]:
    """The cells holding a point within `margin` of the segment a-b (and a few more): column by
    column, the rows the segment spans over the column's reach grown by `margin`, grown by `margin`."""
    (ax, ay), (bx, by) = sorted((a, b))
    for i in range(math.floor((ax - margin) / cell), math.floor((bx + margin) / cell) + 1):
        lo, hi = max(ax, i * cell - margin), min(bx, (i + 1) * cell + margin)
        if bx == ax:
            y0, y1 = min(ay, by), max(ay, by)
        else:
            slope = (by - ay) / (bx - ax)
            y0, y1 = sorted((ay + (lo - ax) * slope, ay + (hi - ax) * slope))
        yield from ((i, j) for j in range(math.floor((y0 - margin) / cell), math.floor((y1 + margin) / cell) + 1))


def _capped(zone: CautionZone | None, max_scale: float) -> CautionZone | None:
    """`zone`, never looser than `max_scale` (the policy's), whatever the store says."""
    if zone is None or zone.speed_scale <= max_scale:
        return zone
    return msgspec.structs.replace(zone, speed_scale=max_scale)


@dataclass(frozen=True, eq=False)
class ZoneMap:
    """Caution zones (oldest first) with a grid of square cells of `cell` m (the clustering radius):
    each zone is listed in the cells its disc overlaps, so a lookup looks only at the zones listed
    in the cells around a point or a leg of a route, not at every zone (`wide`: the few reaching
    over more than MAX_ZONE_CELLS cells, looked at always). Immutable: a change makes a new map
    (sharing the cells it does not touch), which the store swaps in."""

    zones: tuple[CautionZone, ...] = ()
    cell: float = 1.0
    grid: Mapping[Cell, tuple[int, ...]] = field(default_factory=dict)
    wide: tuple[int, ...] = ()

    @classmethod
    def of(cls, zones: Iterable[CautionZone], cell: float | None = None) -> ZoneMap:
        """A map of `zones`; `cell` defaults to the smallest zone radius."""
        listed = tuple(zones)
        size = max(MIN_CELL, cell if cell is not None else min((z.radius for z in listed), default=1.0))
        grid: dict[Cell, tuple[int, ...]] = {}
        wide: list[int] = []
        for i, zone in enumerate(listed):
            _enter(grid, wide, i, zone, size)
        return cls(listed, size, grid, tuple(wide))

    def with_zone(self, i: int, zone: CautionZone) -> ZoneMap:
        """This map with zone `i` replaced by `zone` (`i` = len(zones): added at the end)."""
        grid = dict(self.grid)
        wide = list(self.wide)
        if i < len(self.zones):
            old = self.zones[i]
            cells = _cells(old, self.cell)
            if cells is None:
                wide.remove(i)
            else:
                for c in cells:
                    kept = tuple(j for j in grid.get(c, ()) if j != i)
                    if kept:
                        grid[c] = kept
                    else:
                        grid.pop(c, None)
        _enter(grid, wide, i, zone, self.cell)
        zones = (*self.zones[:i], zone, *self.zones[i + 1 :])
        return ZoneMap(zones, self.cell, grid, tuple(sorted(wide)))

    def __len__(self) -> int:
        return len(self.zones)

    def _listed(self, cells: Iterable[Cell]) -> list[CautionZone]:
        """The zones listed in `cells` (and the wide ones), in the map's order."""
        found: set[int] = set(self.wide)
        for c in cells:
            found.update(self.grid.get(c, ()))
        return [self.zones[i] for i in sorted(found)]

    def at(
        self,
        x: float,
        y: float,
        margin: float,
        max_scale: float = 1.0,
        same: Callable[[CautionZone], bool] | None = None,
    ) -> CautionZone | None:
        """The slowest zone (the first of equals) whose radius grown by `margin` (the base's
        half-diagonal) holds (x, y); `same`: only zones it accepts."""
        found: CautionZone | None = None
        xs, ys = _span(x - margin, y - margin, x + margin, y + margin, self.cell)
        for zone in self._listed((i, j) for i in xs for j in ys):
            if same is not None and not same(zone):
                continue
            if math.hypot(x - zone.x, y - zone.y) <= zone.radius + margin and (
                found is None or zone.speed_scale < found.speed_scale
            ):
                found = zone
        return _capped(found, max_scale)

    def on_route(
        self, points: Sequence[tuple[float, float]], margin: float, max_scale: float = 1.0
    ) -> CautionZone | None:
        """The slowest zone the route (its points in order, the start first) passes within `margin` of."""
        if not points or not self.zones:
            return None
        # A route that does not move (a turn in place) is its start point.
        legs = list(itertools.pairwise(points)) or [(points[0], points[0])]
        cells: set[Cell] = set()
        for a, b in legs:
            cells.update(_leg_cells(a, b, margin, self.cell))
        found: CautionZone | None = None
        for zone in self._listed(cells) if len(cells) <= len(self.grid) else self.zones:
            if found is not None and zone.speed_scale >= found.speed_scale:
                continue
            centre = (zone.x, zone.y)
            if any(_segment_distance(centre, a, b) <= zone.radius + margin for a, b in legs):
                found = zone
        return _capped(found, max_scale)


NO_ZONES = ZoneMap()


def _cells(zone: CautionZone, cell: float) -> list[Cell] | None:
    """The cells a zone's disc overlaps; None for one overlapping more than MAX_ZONE_CELLS."""
    r = zone.radius
    xs, ys = _span(zone.x - r, zone.y - r, zone.x + r, zone.y + r, cell)
    if len(xs) * len(ys) > MAX_ZONE_CELLS:
        return None
    return [(i, j) for i in xs for j in ys]


def _enter(grid: dict[Cell, tuple[int, ...]], wide: list[int], i: int, zone: CautionZone, cell: float) -> None:
    cells = _cells(zone, cell)
    if cells is None:
        wide.append(i)
        return
    for c in cells:
        grid[c] = (*grid.get(c, ()), i)


def _as_map(zones: ZoneMap | Iterable[CautionZone]) -> ZoneMap:
    return zones if isinstance(zones, ZoneMap) else ZoneMap.of(zones)


def zone_at(x: float, y: float, zones: ZoneMap | Iterable[CautionZone], margin: float) -> CautionZone | None:
    """The slowest zone whose radius grown by `margin` (the base's half-diagonal) holds (x, y)."""
    return _as_map(zones).at(x, y, margin)


def _segment_distance(p: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    ax, ay = a
    dx, dy = b[0] - ax, b[1] - ay
    length2 = dx * dx + dy * dy
    s = 0.0 if length2 == 0.0 else max(0.0, min(1.0, ((p[0] - ax) * dx + (p[1] - ay) * dy) / length2))
    return math.hypot(p[0] - (ax + s * dx), p[1] - (ay + s * dy))


def zone_on_route(
    points: Sequence[tuple[float, float]], zones: ZoneMap | Iterable[CautionZone], margin: float
) -> CautionZone | None:
    """The slowest zone the route (its points in order, the start first) passes within `margin` of."""
    return _as_map(zones).on_route(points, margin)


# Plans


@dataclass(frozen=True)
class Place:
    """Somewhere a plan sends the base or the hand: "step 2's goal", "the red cup (step 3)"."""

    what: str
    x: float
    y: float


def _step_places(step: GroundedStep, label: str) -> list[Place]:
    match step:
        case NavigateStep():
            return [Place(f"step {label}'s goal", step.goal.x, step.goal.y)]
        case PickStep():
            return [
                Place(f"step {label}'s approach pose", step.approach.x, step.approach.y),
                Place(f"the {step.object_name} (step {label})", step.position.x, step.position.y),
            ]
        case PlaceStep():
            return [
                Place(f"step {label}'s approach pose", step.approach.x, step.approach.y),
                Place(f"the spot on the {step.surface_name} (step {label})", step.position.x, step.position.y),
            ]
        case _:
            return []


def plan_places(plan: GroundedPlan) -> list[Place]:
    """Every place the plan may send the base (goals, approach poses) and every object or spot its hand
    goes to, on_failure alternatives included, in the plan's order."""
    labels = step_labels(plan)
    places = [p for step, label in zip(plan.steps, labels, strict=True) for p in _step_places(step, label)]
    for fallback in plan.fallbacks:
        for step, label in zip(fallback.steps, fallback_labels(fallback, labels), strict=True):
            places.extend(_step_places(step, label))
    return places


def plan_warnings(
    places: Sequence[Place],
    incidents: Iterable[Incident],
    zones: ZoneMap,
    radius: float,
    margin: float,
    now: float,
    cap: int = MAX_WARNINGS,
    max_scale: float = 1.0,
) -> list[str]:
    """What safety remembers of the plan's places: each caution zone a place of the base's is in, then
    each earlier incident within `radius` of a place, named with the nearest place ("e-stop 2 days ago
    (operator: person in the way), 0.4 m from step 2's goal (2.10, 3.00)"), nearest first. At most
    `cap` lines; the last then says how many more there were. A zone's scale is held to `max_scale`."""
    lines: list[str] = []
    seen_zones: set[tuple[float, float]] = set()
    for place in places:
        zone = zones.at(place.x, place.y, margin, max_scale)
        if zone is not None and (zone.x, zone.y) not in seen_zones:
            seen_zones.add((zone.x, zone.y))
            lines.append(
                f"{place.what} {fmt_point(place.x, place.y)} is in a caution zone ({zone_summary(zone)}): the robot "
                f"keeps to {zone.speed_scale:.0%} of its speed limits there; {clear_hint(zone)}"
            )
    near: list[tuple[float, str]] = []
    for incident in incidents:
        if incident.x is None or incident.y is None or not places:
            continue
        distance, place = min(((math.hypot(incident.x - p.x, incident.y - p.y), p) for p in places), key=lambda d: d[0])
        if distance > radius:
            continue
        reason = f" ({why(incident)})" if why(incident) else ""
        line = (
            f"{KIND_WORDS[incident.kind]} {ago(incident.stamp, now)}{reason}, {distance:.1f} m from {place.what} "
            f"{fmt_point(place.x, place.y)} [incident {incident.id}]"
        )
        near.append((distance, line))
    near.sort(key=lambda d: d[0])
    lines.extend(line for _, line in near)
    if len(lines) <= cap:
        return lines
    more = len(lines) - (cap - 1)
    return [*lines[: cap - 1], f"and {more} more near the plan's places (`tether incidents --near X Y` lists them)"]
