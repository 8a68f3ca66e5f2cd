"""Safety's memory of incidents: what went wrong where, kept across restarts, only ever used to be more
careful. Safety alone writes it; other services report what only they can see (a grasp that failed,
an object dropped, a collision the sim felt) and safety records it with where the robot was."""

from __future__ import annotations

import enum
from typing import Annotated

from msgspec import Meta

from schemas.common import Frozen, Metres, Name, Radians, Text, Vec3

IncidentId = Annotated[int, Meta(ge=1)]
# The most incidents one answer lists (the query's `limit`); `total` says how many matched.
MAX_LISTED = 1000
MAX_INVOLVED = 16
# A caution zone reaches at most this far (m) and names at most this many kinds.
MAX_ZONE_RADIUS = 100.0
MAX_ZONE_KINDS = 8


class IncidentKind(enum.StrEnum):
    """What happened. Safety sees the first five itself; the last three are reported to it."""

    ESTOP = "estop"  # the e-stop latched (`source` says who: operator, executor, agent, watchdog, monitor)
    MONITOR = "monitor"  # a monitor tripped: measured motion beyond a limit, the base in a keep-out zone
    WATCHDOG = "watchdog"  # the robot's state stopped arriving while it moved
    VETO = "veto"  # a motion command of a running plan was vetoed
    NEAR_MISS = "near_miss"  # motion paused for a person closer than the policy's near-miss distance
    GRASP_FAILED = "grasp_failed"  # the executor closed the gripper and the object was not in it
    DROPPED = "dropped"  # an object left the gripper before it was placed
    COLLISION = "collision"  # the sim felt the robot touch a wall, furniture or a person


# The kinds other services may report on safety/incidents/report.
REPORTED_KINDS = frozenset({IncidentKind.GRASP_FAILED, IncidentKind.DROPPED, IncidentKind.COLLISION})

InvolvedNames = Annotated[list[Name], Meta(max_length=MAX_INVOLVED)]


class Incident(Frozen):
    """One incident as the store keeps it. `x`, `y`, `yaw`: the base on the map when it happened (None:
    safety had no recent pose); `hand`: the grasp point on the map (None: unknown); `source`: who
    triggered or reported it; `rule`: the safety rule that decided, when one did; `goal_id`, `step`,
    `label`: the plan and step running; `objects`, `people`: what was involved (the object in the hand
    or named by the step; people within the near-miss distance); `recording`: the MCAP file the
    recorder was writing then ("" when none was known); `cleared`: an operator cleared the caution
    zone it counted towards (it still warns, it no longer slows the robot)."""

    id: IncidentId
    stamp: float
    kind: IncidentKind
    reason: Text = ""
    x: Metres | None = None
    y: Metres | None = None
    yaw: Radians | None = None
    hand: Vec3 | None = None
    source: Annotated[str, Meta(max_length=64)] = ""
    rule: Annotated[str, Meta(max_length=64)] = ""
    goal_id: Annotated[str, Meta(max_length=64)] = ""
    step: Annotated[int, Meta(ge=0)] | None = None
    label: Annotated[str, Meta(max_length=64)] = ""
    objects: InvolvedNames = []
    people: InvolvedNames = []
    recording: Annotated[str, Meta(max_length=400)] = ""
    cleared: bool = False


class IncidentReport(Frozen):
    """From the executor or the sim: something safety cannot see happened. `kind` must be one of
    REPORTED_KINDS; `x`, `y`: where, when the reporter knows better than the robot's pose (a dropped
    object's position); safety adds the pose, the hand, the plan and the recording."""

    kind: IncidentKind
    reason: Text
    objects: InvolvedNames = []
    people: InvolvedNames = []
    goal_id: Annotated[str, Meta(max_length=64)] = ""
    step: Annotated[int, Meta(ge=0)] | None = None
    label: Annotated[str, Meta(max_length=64)] = ""
    x: Metres | None = None
    y: Metres | None = None


class IncidentQuery(Frozen):
    """Which incidents to list, newest first. `x`, `y` with `radius`: only those within it (both or
    neither); `kinds`: only these (empty: all); `since`: wall clock seconds; `id`: just that one."""

    x: Metres | None = None
    y: Metres | None = None
    radius: Annotated[float, Meta(gt=0.0, le=1000.0)] = 2.0
    kinds: Annotated[list[IncidentKind], Meta(max_length=8)] = []
    since: Annotated[float, Meta(ge=0.0)] = 0.0
    id: IncidentId | None = None
    limit: Annotated[int, Meta(ge=1, le=MAX_LISTED)] = 100


class CautionZone(Frozen):
    """A place with `count` incidents (not cleared) within `radius` of (x, y): the robot keeps to
    `speed_scale` of its speed limits inside it until an operator clears it. `incidents`: their ids;
    `kinds`: their kinds, the most frequent first (empty: not known)."""

    x: Metres
    y: Metres
    radius: Annotated[float, Meta(gt=0.0, le=MAX_ZONE_RADIUS)]
    count: Annotated[int, Meta(ge=1)]
    speed_scale: Annotated[float, Meta(ge=0.0, le=1.0)]
    incidents: Annotated[list[IncidentId], Meta(max_length=MAX_LISTED)] = []
    last: float = 0.0
    kinds: Annotated[list[IncidentKind], Meta(max_length=MAX_ZONE_KINDS)] = []


class IncidentList(Frozen):
    """The answer to an IncidentQuery. `total`: how many matched before the limit; `zones`: the caution
    zones in force; `store`: the store's fault ("" when it is healthy): safety keeps checking with its
    limits when the store cannot be read or written."""

    incidents: Annotated[list[Incident], Meta(max_length=MAX_LISTED)] = []
    total: Annotated[int, Meta(ge=0)] = 0
    zones: Annotated[list[CautionZone], Meta(max_length=MAX_LISTED)] = []
    store: Text = ""


class ForgetAction(enum.StrEnum):
    FORGET = "forget"  # the incident is gone from memory: it no longer warns or counts
    CLEAR = "clear"  # the caution zone the incident counts towards is cleared: its incidents still warn


class ForgetIncident(Frozen):
    """An operator forgets an incident, or clears the caution zone it is in, with the operator's token
    and a reason (recorded as a safety event)."""

    operator: Name
    token: Annotated[str, Meta(max_length=256)]
    id: IncidentId
    reason: Annotated[str, Meta(min_length=1, max_length=4000)]
    action: ForgetAction = ForgetAction.FORGET


class ForgetReply(Frozen):
    """`changed`: the incidents forgotten or cleared."""

    ok: bool
    message: Text
    changed: Annotated[list[IncidentId], Meta(max_length=MAX_LISTED)] = []
