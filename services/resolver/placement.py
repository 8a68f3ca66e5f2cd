"""Where on a table top to put something down: near the edge the robot stands at, clear of the rest."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from schemas.common import Vec3
from schemas.world import Furniture
from services.worldmodel import approach_axes

# How far apart the candidate spots along an edge are tried.
SEARCH_STEP = 0.05


def _offsets(low: float, high: float, start: float) -> list[float]:
    """Points in [low, high], starting at `start` (clamped) and fanning out both ways."""
    if low > high:
        return [(low + high) / 2]
    start = min(max(start, low), high)
    points = [start]
    k = 1
    while start - k * SEARCH_STEP >= low - 1e-9 or start + k * SEARCH_STEP <= high + 1e-9:
        for p in (start + k * SEARCH_STEP, start - k * SEARCH_STEP):
            if low - 1e-9 <= p <= high + 1e-9:
                points.append(p)
        k += 1
    return points


def place_position(
    surface: Furniture,
    occupied: Sequence[tuple[float, float]],
    *,
    inset: float,
    clearance: float,
    near: tuple[float, float] | None = None,
    allowed: Callable[[float, float], bool] | None = None,
) -> Vec3 | None:
    """A spot on `surface`'s top, `inset` in from the edge nearest its approach pose, at least
    `clearance` (xy) from every occupied point, shifted sideways along the edge (then further in)
    as needed; with `near`, the free spot closest to that point instead. Only spots (x, y) that
    `allowed` accepts, when given. None when the top has no such spot."""
    cx, cy = surface.center
    half = (surface.size.x / 2, surface.size.y / 2)
    ax, ay = surface.approach.x, surface.approach.y
    across, along = approach_axes(surface)
    centre = (cx, cy)
    approach = (ax, ay)
    sign = 1.0 if approach[across] >= centre[across] else -1.0
    edge = centre[across] + sign * half[across]
    depths = _offsets(inset, 2 * half[across] - inset, inset)
    depths = sorted(d for d in depths if d >= inset - 1e-9) or [half[across]]
    sideways = _offsets(centre[along] - half[along] + inset, centre[along] + half[along] - inset, approach[along])
    free = []
    for depth in depths:
        for side in sideways:
            point = [0.0, 0.0]
            point[across] = edge - sign * depth
            point[along] = side
            if all(math.dist(point, other) >= clearance - 1e-9 for other in occupied) and (
                allowed is None or allowed(point[0], point[1])
            ):
                free.append((point[0], point[1]))
    if not free:
        return None
    x, y = free[0] if near is None else min(free, key=lambda p: math.dist(p, near))
    return Vec3(x=round(x, 3), y=round(y, 3), z=round(surface.size.z, 3))
