"""What perception has seen: objects where last seen, refined over sightings, stale when unseen for long."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import msgspec

from schemas.common import Vec3
from schemas.world import PerceivedObject, PerceivedObjects

GRIPPER = "gripper"
# Sightings averaged into a remembered position at most: older ones then weigh less and less, so a
# position that creeps (within tolerance each frame) is still followed.
MAX_AVERAGED = 20
# Objects remembered at most; beyond that those seen longest ago are forgotten (a publisher inventing
# ids must not grow the resolver without bound). A real scene has far fewer.
MAX_OBJECTS = 1000


@dataclass(frozen=True)
class Origin:
    """Where an object was last seen before it entered the gripper: on a furniture top (`on`), or
    on the floor (`on` None)."""

    on: str | None
    position: Vec3


@dataclass
class _Sighting:
    """One remembered object: its latest report, its refined position, and when it was last seen."""

    report: PerceivedObject  # the latest sighting as reported (name, class, colour, room, on)
    position: Vec3  # the running average of the sightings since it last moved
    averaged: int
    seen_at: float  # monotonic receive time
    stamp: float  # the stamp of the frame it was last seen in
    released: bool = False  # let go by the gripper out of view: where it went is not known
    stale: bool = False  # as of the last refresh
    anchor: Vec3 | None = None  # the position when `version` last changed for it


class ObjectMemory:
    """Objects where perception last saw them. Pure: callers pass `now`, a monotonic time in seconds.

    `version` changes exactly when what the resolver would believe changes: the first frame, an
    object first seen, moved beyond `move_tolerance` (xy or z), onto something else, released from
    the gripper, turned stale or fresh again, or forgotten. Sightings within tolerance refine the
    position without changing it, until the refined position has gone `move_tolerance` from where it
    stood when `version` last changed for it (an object creeping a millimetre a frame). Not
    thread-safe: the caller holds a lock.
    """

    def __init__(self, stale_after: float, move_tolerance: float, known: Iterable[str] | None = None) -> None:
        if not stale_after > 0.0 or not move_tolerance > 0.0:
            raise ValueError(f"stale_after ({stale_after}) and move_tolerance ({move_tolerance}) must be positive")
        self.stale_after = stale_after
        self.move_tolerance = move_tolerance
        # The ids worth remembering (the world's objects; None: every id). Others have no name to be
        # referred to by, and a flood of them must not push out what the camera saw of real ones.
        self._known = frozenset(known) if known is not None else None
        self.version = 0
        self._objects: dict[str, _Sighting] = {}
        self._origins: dict[str, Origin] = {}
        self._stamp: float | None = None  # the latest frame's stamp; None before any frame

    def __len__(self) -> int:
        return len(self._objects)

    def update(self, frame: PerceivedObjects, now: float) -> None:
        """Take in one camera frame received at `now`. An id listed twice in it counts once, as first listed."""
        changed = self._stamp is None
        self._stamp = frame.stamp
        in_frame: set[str] = set()
        for seen in frame.objects:
            if self._known is not None and seen.id not in self._known:
                continue
            if seen.id not in in_frame:
                in_frame.add(seen.id)
                changed |= self._sighted(seen, frame.stamp, now)
        # The camera always reports what the gripper holds: a held object missing from the frame was
        # let go out of view.
        for object_id, sighting in self._objects.items():
            if sighting.report.on == GRIPPER and object_id not in in_frame:
                sighting.report = _replace(sighting.report, on=None)
                sighting.released = True
                changed = True
        changed |= self._forget_oldest()
        changed |= self._restale(now)
        if changed:
            self.version += 1

    def refresh(self, now: float) -> None:
        """Turn objects stale (or fresh) as of `now`; `version` changes if any did."""
        if self._restale(now):
            self.version += 1

    def snapshot(self, now: float) -> PerceivedObjects | None:
        """Every remembered object as of `now`, for the resolver; None before the first frame.

        Each object's `stamp` is the stamp of the frame it was last seen in; ages are measured on
        the monotonic `now`, never on stamps (they come from another machine's clock)."""
        if self._stamp is None:
            return None
        self.refresh(now)
        objects = [
            _replace(s.report, position=s.position, stamp=s.stamp, stale=s.stale) for s in self._objects.values()
        ]
        return PerceivedObjects(stamp=self._stamp, objects=objects)

    def origins(self) -> dict[str, Origin]:
        """For each object in the gripper, where it was last seen before it got there (when it was
        seen at all): what "put it back" means for an object a plan starts out holding."""
        return {
            object_id: origin
            for object_id, origin in self._origins.items()
            if object_id in self._objects and self._objects[object_id].report.on == GRIPPER
        }

    def _sighted(self, seen: PerceivedObject, stamp: float, now: float) -> bool:
        """Remember one sighting; True when it changes what is believed (new, moved, or on something else)."""
        known = self._objects.get(seen.id)
        if seen.on == GRIPPER and (known is None or known.report.on != GRIPPER):
            if known is not None and not known.released:
                self._origins[seen.id] = Origin(known.report.on, known.position)
            else:
                self._origins.pop(seen.id, None)  # where it was before is not known
        if known is None or known.released or seen.on != known.report.on or not self._near(known.position, seen):
            self._objects[seen.id] = _Sighting(seen, seen.position, 1, now, stamp, anchor=seen.position)
            return True
        known.averaged = min(known.averaged + 1, MAX_AVERAGED)
        known.position = _towards(known.position, seen.position, 1.0 / known.averaged)
        known.report = seen
        known.seen_at = now
        known.stamp = stamp
        # An object creeping within tolerance at every sighting is followed by the average: once that
        # has gone `move_tolerance` from where it was last believed, it is believed somewhere new
        # (else answers cached for the old place were given for ever).
        if known.anchor is not None and self._within(known.anchor, known.position):
            return False
        known.anchor = known.position
        return True

    def _near(self, remembered: Vec3, seen: PerceivedObject) -> bool:
        return self._within(remembered, seen.position)

    def _within(self, a: Vec3, b: Vec3) -> bool:
        """Whether `b` is within `move_tolerance` of `a`, in xy and in z."""
        return math.hypot(b.x - a.x, b.y - a.y) <= self.move_tolerance and abs(b.z - a.z) <= self.move_tolerance

    def _restale(self, now: float) -> bool:
        flipped = False
        for sighting in self._objects.values():
            stale = sighting.released or now - sighting.seen_at > self.stale_after
            if stale != sighting.stale:
                sighting.stale = stale
                flipped = True
        return flipped

    def _forget_oldest(self) -> bool:
        excess = len(self._objects) - MAX_OBJECTS
        if excess <= 0:
            return False
        oldest = sorted(self._objects, key=lambda object_id: self._objects[object_id].seen_at)[:excess]
        for object_id in oldest:
            del self._objects[object_id]
            self._origins.pop(object_id, None)
        return True


def _towards(a: Vec3, b: Vec3, weight: float) -> Vec3:
    return Vec3(x=a.x + (b.x - a.x) * weight, y=a.y + (b.y - a.y) * weight, z=a.z + (b.z - a.z) * weight)


def _replace(obj: PerceivedObject, **changes: Any) -> PerceivedObject:
    return msgspec.structs.replace(obj, **changes)
