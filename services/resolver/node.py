"""The resolver on the wire: Plan on plan/resolve, grounded with remembered perception and the latest
odometry; the scene it sees on world/scene."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from schemas import keys
from schemas.common import Pose2D, ServiceError
from schemas.plan import Plan, ResolveReply
from schemas.robot import Odometry
from schemas.world import Empty, PerceivedHumans, PerceivedObjects, SceneDescription
from services.resolver.cache import ResolutionCache, WorldKey, world_key
from services.resolver.config import ResolverConfig
from services.resolver.memory import ObjectMemory, Origin
from services.resolver.resolver import Resolver, answer
from services.runtime import Node, encode
from services.worldmodel import WorldModel, load_world

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Snapshot:
    """What the resolver believes at one moment: objects where last seen (and where each held one
    was before the gripper took it), the robot, the people."""

    objects: PerceivedObjects | None
    robot: Pose2D | None
    humans: PerceivedHumans | None
    key: WorldKey
    origins: dict[str, Origin]


class Perception:
    """Perception remembered, the newest odometry and people; written by subscribers, read per query."""

    def __init__(self, memory: ObjectMemory, clock: Callable[[], float] = time.monotonic) -> None:
        self._lock = threading.Lock()
        self._memory = memory
        self._clock = clock
        self._robot: Pose2D | None = None
        self._humans: PerceivedHumans | None = None

    def on_objects(self, message: PerceivedObjects) -> None:
        with self._lock:
            self._memory.update(message, self._clock())

    def on_odom(self, message: Odometry) -> None:
        with self._lock:
            self._robot = message.pose

    def on_humans(self, message: PerceivedHumans) -> None:
        with self._lock:
            self._humans = message

    def snapshot(self) -> Snapshot:
        with self._lock:
            objects = self._memory.snapshot(self._clock())
            key = world_key(self._memory.version, self._robot, self._humans)
            return Snapshot(objects, self._robot, self._humans, key, self._memory.origins())


def build_resolver(config: ResolverConfig) -> Resolver:
    return Resolver(WorldModel(load_world(config.world)), config)


def build_perception(config: ResolverConfig) -> Perception:
    return Perception(ObjectMemory(stale_after=config.stale_after, move_tolerance=config.move_tolerance))


def handler(resolver: Resolver, perception: Perception, cache: ResolutionCache) -> Callable[[Plan], ResolveReply]:
    """A handler that always answers: a GroundedPlan, or a ServiceError naming the step."""

    def handle(plan: Plan) -> ResolveReply:
        snap = perception.snapshot()
        request = encode(plan)
        cached = cache.get(snap.key, request)
        if cached is not None:
            log.debug("grounded plan of %d steps from the cache (%d hits)", len(cached.steps), cache.hits)
            return cached
        reply = answer(resolver, plan, snap.objects, snap.robot, snap.humans, snap.origins)
        if isinstance(reply, ServiceError):
            log.info("refused plan: %s", reply.message)
        else:
            cache.put(snap.key, request, reply)
            log.info("grounded plan of %d steps", len(reply.steps))
        return reply

    return handle


def scene_handler(resolver: Resolver, perception: Perception) -> Callable[[Empty], SceneDescription]:
    """world/scene: the scene as the next plan would be resolved in it."""

    def handle(_request: Empty) -> SceneDescription:
        snap = perception.snapshot()
        return resolver.describe(snap.objects, snap.robot, humans=snap.humans, stamp=time.time())

    return handle


def declare(node: Node, resolver: Resolver, config: ResolverConfig) -> Perception:
    perception = build_perception(config)
    node.subscribe(keys.OBJECTS, perception.on_objects)
    node.subscribe(keys.ODOM, perception.on_odom)
    node.subscribe(keys.HUMANS, perception.on_humans)
    node.serve(keys.PLAN_RESOLVE, handler(resolver, perception, ResolutionCache(config.cache_size)))
    node.serve(keys.SCENE, scene_handler(resolver, perception))
    return perception
