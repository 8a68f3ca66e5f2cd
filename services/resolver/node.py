"""The resolver on the wire: Plan on plan/resolve, grounded with remembered perception and the latest
odometry; the scene it sees on world/scene."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from schemas import keys
from schemas.common import Pose2D, ServiceError
from schemas.plan import Plan, ResolveReply
from schemas.robot import Odometry
from schemas.world import Empty, PerceivedHuman, PerceivedHumans, PerceivedObjects, SceneDescription
from services.resolver.cache import ResolutionCache, WorldKey, world_key
from services.resolver.config import ODOM_MAX_AGE, ResolverConfig
from services.resolver.memory import ObjectMemory, Origin
from services.resolver.resolver import Resolver, answer
from services.runtime import Node, encode
from services.worldmodel import WorldModel, load_world

log = logging.getLogger(__name__)
# People remembered by id at most (a real scene has a handful); the longest unseen go first.
MAX_PEOPLE = 256


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
    """Perception remembered, the newest odometry and each person where last seen; written by
    subscribers, read per query.

    Odometry older than `odom_max_age` (on `clock`, when it arrived) is no pose at all: a move
    relative to the robot is refused rather than grounded from where it stood an hour ago. A person
    missing from the latest report (out of view: a people tracker lists only whom it sees) stays
    where last seen, not where the world file puts them; a report naming one id at two poses moves
    no one of that id (which is meant is not known) and is logged. A person reported where `on_map`
    says no sighting can be stays where last believably seen; the report is kept beside it until a
    believable one comes, so the resolver warns of it. `people`: the ids worth remembering (the
    world's people; None: every id)."""

    def __init__(
        self,
        memory: ObjectMemory,
        clock: Callable[[], float] = time.monotonic,
        odom_max_age: float = ODOM_MAX_AGE,
        people: Iterable[str] | None = None,
        on_map: Callable[[float, float], bool] = lambda x, y: True,
    ) -> None:
        self._lock = threading.Lock()
        self._memory = memory
        self._clock = clock
        self._odom_max_age = odom_max_age
        # Only a person of the world has a name a plan can refer to: a tracker's (or a hostile
        # peer's) made-up ids would otherwise push out where the operator was last seen.
        self._known_people = frozenset(people) if people is not None else None
        self._robot: tuple[float, Pose2D] | None = None  # when it arrived, the pose
        self._on_map = on_map
        self._people: dict[str, PerceivedHuman] = {}  # by id, as last believably seen
        # By id, a report off the map since the last believable one, kept apart for the resolver's
        # warning: kept as last seen, it sent "come to me" to the world file's pose instead.
        self._doubted: dict[str, PerceivedHuman] = {}
        self._people_stamp: float | None = None  # of the latest report; None before any

    def on_objects(self, message: PerceivedObjects) -> None:
        with self._lock:
            self._memory.update(message, self._clock())

    def on_odom(self, message: Odometry) -> None:
        with self._lock:
            self._robot = (self._clock(), message.pose)

    def on_humans(self, message: PerceivedHumans) -> None:
        known = self._known_people
        humans = [h for h in message.humans if known is None or h.id in known]
        poses: dict[str, set[tuple[float, float, float]]] = {}
        for human in humans:
            poses.setdefault(human.id, set()).add((human.pose.x, human.pose.y, human.pose.yaw))
        twice = sorted(i for i, p in poses.items() if len(p) > 1)
        if twice:
            log.warning("people reported at two poses at once, not moved: %s", ", ".join(twice[:5]))
        believable = {h.id: self._on_map(h.pose.x, h.pose.y) for h in humans if h.id not in twice}
        with self._lock:
            self._people_stamp = message.stamp
            for human in humans:
                if human.id in twice:
                    continue
                self._doubted.pop(human.id, None)
                kept = self._people if believable[human.id] else self._doubted
                kept.pop(human.id, None)  # to the end: each dict runs from longest unseen
                kept[human.id] = human
            for remembered in (self._people, self._doubted):
                while len(remembered) > MAX_PEOPLE:  # ids invented without end must not grow it
                    del remembered[next(iter(remembered))]

    def snapshot(self) -> Snapshot:
        with self._lock:
            now = self._clock()
            objects = self._memory.snapshot(now)
            robot = None
            if self._robot is not None and now - self._robot[0] <= self._odom_max_age:
                robot = self._robot[1]
            humans = None
            key: WorldKey = world_key(self._memory.version, robot, None)
            if self._people_stamp is not None:
                believed = PerceivedHumans(stamp=self._people_stamp, humans=list(self._people.values()))
                doubted = PerceivedHumans(stamp=self._people_stamp, humans=list(self._doubted.values()))
                # Both for the resolver: it believes the one on the map and warns of the other.
                humans = PerceivedHumans(stamp=self._people_stamp, humans=believed.humans + doubted.humans)
                # Both in the key too (the cache's reads one pose per id): a warning of one report, or
                # a goal at one believed pose, is never served for another.
                version = self._memory.version
                key = (world_key(version, robot, believed), world_key(version, robot, doubted))
            return Snapshot(objects, robot, humans, key, self._memory.origins())


def build_resolver(config: ResolverConfig) -> Resolver:
    return Resolver(WorldModel(load_world(config.world)), config)


def build_perception(
    config: ResolverConfig,
    known: Iterable[str],
    people: Iterable[str],
    on_map: Callable[[float, float], bool] = lambda x, y: True,
) -> Perception:
    """`known`, `people`: the world's object and person ids, the only ones remembered; `on_map`:
    where a person may believably be seen (the resolver's map check)."""
    memory = ObjectMemory(stale_after=config.stale_after, move_tolerance=config.move_tolerance, known=known)
    return Perception(memory, odom_max_age=config.odom_max_age, people=people, on_map=on_map)


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
    world = resolver.world
    perception = build_perception(
        config, (o.id for o in world.objects), (h.id for h in world.humans), on_map=resolver.on_map
    )
    node.subscribe(keys.OBJECTS, perception.on_objects)
    node.subscribe(keys.ODOM, perception.on_odom)
    node.subscribe(keys.HUMANS, perception.on_humans)
    node.serve(keys.PLAN_RESOLVE, handler(resolver, perception, ResolutionCache(config.cache_size)))
    node.serve(keys.SCENE, scene_handler(resolver, perception))
    return perception
