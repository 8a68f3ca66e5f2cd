"""Where to look, in order, for an object that is not in view: the search's places within its bounds."""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass

from schemas.common import Pose2D
from schemas.world import Furniture
from services.executor.config import SEARCH_SCOPES, SearchScope
from services.worldmodel import WorldModel, approach_axes


@dataclass(frozen=True)
class Look:
    """One place of a search. `poses` are where the base stands to look, in order: the headings of
    a look around (turns in place), or the approach pose of the furniture `surface`. `place` says
    it in the words of a report: "around in the kitchen", "on the kitchen table"."""

    place: str
    poses: tuple[Pose2D, ...]
    surface: str | None = None


def narrowest(scope: SearchScope, *others: SearchScope | None) -> SearchScope:
    """The narrowest of the scopes given (None: no say)."""
    given = [s for s in (scope, *others) if s is not None]
    return min(given, key=SEARCH_SCOPES.index)


@dataclass(frozen=True)
class SearchPlan:
    """The places to look, in order; `left_out` places within the scope did not fit in
    `max_places`; `out_of_scope` furniture tops lie in rooms the scope leaves out."""

    looks: list[Look]
    scope: SearchScope
    max_places: int
    left_out: int = 0
    out_of_scope: int = 0


def plan_search(
    world: WorldModel,
    here: Pose2D,
    *,
    scope: SearchScope,
    max_places: int,
    headings: int,
    remembered_on: str | None = None,
    skip: Collection[str] = (),
    clearance: float = 0.04,
    surface_view: float = 1.2,
) -> SearchPlan:
    """The places to look from `here`, at most `max_places`: a look around (from here when the base
    can turn in place with `clearance` to spare, else from its room's pose), then the furniture tops
    of its room, then (scope "flat") those of the other rooms; `remembered_on` (where memory last
    saw the object) first among its room's, the rest nearest first from the previous stop, room by
    room. A top longer than `surface_view` is looked at from its approach pose and then from along
    its edge towards each end; of one in `skip` (looked at from its approach pose already) only the
    ends are left to look from, and a short one in `skip` is left out."""
    # A top looked at from its approach pose already is left out, or, if long, looked along (its ends).
    surfaces = [f for f in world.world.furniture if f.id not in skip or len(surface_poses(world, f, surface_view)) > 1]
    if scope == "none":
        return SearchPlan([], scope, max_places, out_of_scope=len(surfaces))
    room = world.room_of(here.x, here.y)
    looks: list[Look] = []
    around = _look_around(world, here, room, headings, clearance)
    if around is not None:
        looks.append(around)
    start = around.poses[-1] if around is not None else here
    in_room = [f for f in surfaces if room is not None and world.room_of(*f.center) == room]
    others = [f for f in surfaces if f not in in_room]
    ordered = _tour(world, in_room, start, remembered_on)
    if scope == "flat":
        last = ordered[-1].approach if ordered else start
        ordered += _tour(world, others, last, remembered_on)
    for f in ordered:
        poses = surface_poses(world, f, surface_view)
        if f.id in skip:
            looks.append(Look(f"along the {f.name}", poses[1:], f.id))
        else:
            looks.append(Look(f"on the {f.name}", poses, f.id))
    return SearchPlan(
        looks[:max_places],
        scope,
        max_places,
        left_out=max(0, len(looks) - max_places),
        out_of_scope=len(others) if scope == "room" else 0,
    )


def surface_poses(world: WorldModel, item: Furniture, view: float) -> tuple[Pose2D, ...]:
    """Where the base stands to look at a furniture top: its approach pose, and when the edge it
    faces is longer than `view` (metres of it one look takes in), also the poses along that edge
    towards each end, so that nothing near an end is outside the camera's view."""
    _, along = approach_axes(item)
    length = (item.size.x, item.size.y)[along]
    if length <= view:
        return (item.approach,)
    ends = []
    for sign in (-1.0, 1.0):
        point = list(item.center)
        point[along] += sign * (length - view) / 2
        ends.append(world.approach_near(item.id, point[0], point[1]))
    return (item.approach, *ends)


def not_found(name: str, searched: list[str], plan: SearchPlan, time_limit: float | None = None) -> str:
    """Why the search ends without the object: every place looked, in order, then the bound that
    stopped it (`time_limit`: it ran out of time) or the places its scope left out."""
    looked = f"looked {', '.join(searched)}" if searched else "looked nowhere"
    limits = []
    if plan.scope == "none":
        limits.append("no search (search scope none)")
    if time_limit is not None:
        limits.append(f"the search stopped after its {time_limit:g} s")
    elif plan.left_out:
        limits.append(f"{plan.left_out} more place(s) not visited (the search visits at most {plan.max_places})")
    if plan.out_of_scope and plan.scope == "room":
        limits.append("other rooms not searched (search scope room)")
    return f"{name} not found: {looked}" + "".join(f"; {limit}" for limit in limits)


def step_scope(step: object) -> SearchScope | None:
    """The scope a plan step asks for (its `search` parameter), if any: it can only narrow the
    configured one."""
    scope = getattr(step, "search", None)
    return next((s for s in SEARCH_SCOPES if s == scope), None)


def _look_around(world: WorldModel, here: Pose2D, room: str | None, headings: int, clearance: float) -> Look | None:
    """Turns through `headings` directions round the circle: from here (its heading is looked at
    already), or from the room's pose when the base cannot turn here; None outside every room when
    it cannot turn."""
    step = math.tau / headings
    if _can_turn(world, here, room, clearance):
        poses = [_heading(here, here.yaw + k * step) for k in range(1, headings)]
    elif room is not None:
        centre = world.room_pose(room)
        poses = [_heading(centre, centre.yaw + k * step) for k in range(headings)]
    else:
        return None
    names = {r.id: r.name for r in world.world.rooms}
    where = f"in the {names[room]}" if room is not None else "where it stood"
    return Look(place=f"around {where}", poses=tuple(poses))


def _can_turn(world: WorldModel, here: Pose2D, room: str | None, clearance: float) -> bool:
    """Whether the base turns round where it stands without touching anything (the circle of its
    half diagonal, with `clearance`, free of walls, furniture and keep-out zones)."""
    if room is None:
        return False
    spot = world.free_spot(here.x, here.y, world.base_radius + clearance, world.room_shapes[room])
    return spot is not None and math.dist(spot, (here.x, here.y)) < 1e-9


def _heading(at: Pose2D, yaw: float) -> Pose2D:
    return Pose2D(x=at.x, y=at.y, yaw=round(math.remainder(yaw, math.tau), 4))


def _tour(world: WorldModel, items: list[Furniture], start: Pose2D, first: str | None) -> list[Furniture]:
    """`items` in visiting order: `first` (if among them), then always the nearest to the previous
    stop, staying in the previous stop's room while it has some left."""
    left = list(items)
    order: list[Furniture] = []
    at, room = (start.x, start.y), world.room_of(start.x, start.y)
    while left:
        chosen = next((f for f in left if f.id == first), None) if not order else None
        if chosen is None:
            chosen = min(
                left,
                key=lambda f: (world.room_of(*f.center) != room, math.dist(at, (f.approach.x, f.approach.y)), f.id),
            )
        left.remove(chosen)
        order.append(chosen)
        at, room = (chosen.approach.x, chosen.approach.y), world.room_of(*chosen.center)
    return order
