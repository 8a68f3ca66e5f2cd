"""Successful resolutions kept for identical plans while the world the resolver believes stays the same."""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Hashable

from schemas.common import Pose2D
from schemas.plan import GroundedPlan, ResolveReply
from schemas.world import PerceivedHumans

# Poses closer than these count as the same world: odometry and people jitter by less.
ROBOT_STEP = 0.01  # metres
ROBOT_YAW_STEP = 0.01  # radians
HUMAN_STEP = 0.05  # metres
HUMAN_YAW_STEP = 0.05  # radians
# Bigger plans are resolved every time rather than kept (a cache entry holds the plan twice).
MAX_CACHED_PLAN_BYTES = 64 * 1024

WorldKey = Hashable


def world_key(memory_version: int, robot: Pose2D | None, humans: PerceivedHumans | None) -> WorldKey:
    """What a resolution depends on besides the plan: the object memory's version, the robot's pose
    to 1 cm and 0.01 rad, and each person's pose to 5 cm and 0.05 rad (None: not known)."""
    return (memory_version, _pose(robot, ROBOT_STEP, ROBOT_YAW_STEP), _humans(humans))


def _pose(pose: Pose2D | None, step: float, yaw_step: float) -> tuple[int, int, int] | None:
    if pose is None:
        return None
    yaw = math.atan2(math.sin(pose.yaw), math.cos(pose.yaw))
    return round(pose.x / step), round(pose.y / step), round(yaw / yaw_step)


def _humans(humans: PerceivedHumans | None) -> tuple[tuple[str, tuple[int, int, int] | None], ...] | None:
    if humans is None:
        return None
    # As the resolver reads them: by id, the last report of an id winning.
    poses = {h.id: h.pose for h in humans.humans}
    return tuple(sorted((i, _pose(p, HUMAN_STEP, HUMAN_YAW_STEP)) for i, p in poses.items()))


class ResolutionCache:
    """An LRU of GroundedPlans by (world key, plan bytes); refusals are never kept. Look up with `get`,
    then `put` what was resolved on a miss.

    Entries of an older world key can never match again, so a `get` with a new world key drops them all.
    `size` 0 disables the cache. Safe to share across the threads that answer queries.
    """

    def __init__(self, size: int) -> None:
        if size < 0:
            raise ValueError(f"cache size {size} must be 0 or more")
        self.size = size
        self.hits = 0
        self.misses = 0
        self._world: WorldKey | None = None
        self._entries: OrderedDict[bytes, GroundedPlan] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    def get(self, world: WorldKey, plan: bytes) -> GroundedPlan | None:
        if self.size == 0:
            return None
        with self._lock:
            self._enter(world)
            found = self._entries.get(plan)
            if found is None:
                self.misses += 1
                return None
            self._entries.move_to_end(plan)
            self.hits += 1
            return found

    def put(self, world: WorldKey, plan: bytes, reply: ResolveReply) -> None:
        """Keep `reply` if it is a GroundedPlan of a plan not too big, resolved in the current world.

        The current world is the one of the latest `get`: a reply resolved in a world that has
        changed since (a query overtaken by a newer one) is not kept, and does not evict the newer
        world's entries."""
        if self.size == 0 or not isinstance(reply, GroundedPlan) or len(plan) > MAX_CACHED_PLAN_BYTES:
            return
        with self._lock:
            if world != self._world:
                return
            self._entries[plan] = reply
            self._entries.move_to_end(plan)
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)

    def _enter(self, world: WorldKey) -> None:
        if world != self._world:
            self._entries.clear()
            self._world = world
