"""The resolver on the wire: Plan on plan/resolve, grounded with the latest perception and odometry."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from schemas import keys
from schemas.common import Pose2D, ServiceError
from schemas.plan import Plan, ResolveReply
from schemas.robot import Odometry
from schemas.world import PerceivedHumans, PerceivedObjects
from services.resolver.config import ResolverConfig
from services.resolver.resolver import Resolver, answer
from services.runtime import Node
from services.worldmodel import WorldModel, load_world

log = logging.getLogger(__name__)


class Latest:
    """The newest perception, odometry and people seen; written by subscribers, read per query."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._objects: PerceivedObjects | None = None
        self._robot: Pose2D | None = None
        self._humans: PerceivedHumans | None = None

    def on_objects(self, message: PerceivedObjects) -> None:
        with self._lock:
            self._objects = message

    def on_odom(self, message: Odometry) -> None:
        with self._lock:
            self._robot = message.pose

    def on_humans(self, message: PerceivedHumans) -> None:
        with self._lock:
            self._humans = message

    def snapshot(self) -> tuple[PerceivedObjects | None, Pose2D | None, PerceivedHumans | None]:
        with self._lock:
            return self._objects, self._robot, self._humans


def build_resolver(config: ResolverConfig) -> Resolver:
    return Resolver(
        WorldModel(load_world(config.world)),
        place_inset=config.place_inset,
        place_clearance=config.place_clearance,
        human_standoff=config.human_standoff,
        object_standoff=config.object_standoff,
    )


def handler(resolver: Resolver, latest: Latest) -> Callable[[Plan], ResolveReply]:
    """A handler that always answers: a GroundedPlan, or a ServiceError naming the step."""

    def handle(plan: Plan) -> ResolveReply:
        objects, robot, humans = latest.snapshot()
        reply = answer(resolver, plan, objects, robot, humans)
        if isinstance(reply, ServiceError):
            log.info("refused plan: %s", reply.message)
        else:
            log.info("grounded plan of %d steps", len(reply.steps))
        return reply

    return handle


def declare(node: Node, resolver: Resolver) -> Latest:
    latest = Latest()
    node.subscribe(keys.OBJECTS, latest.on_objects)
    node.subscribe(keys.ODOM, latest.on_odom)
    node.subscribe(keys.HUMANS, latest.on_humans)
    node.serve(keys.PLAN_RESOLVE, handler(resolver, latest))
    return latest
