"""The translation cache: identical plans in an unchanged world, never refusals, dropped when the world changes."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import cast

import msgspec
import pytest

from schemas.common import ErrorKind, Pose2D, ServiceError, Vec3
from schemas.plan import Action, GroundedPlan, Plan, Step, WaitStep
from schemas.robot import Odometry
from schemas.world import PerceivedHuman, PerceivedHumans, PerceivedObject, PerceivedObjects
from services.resolver.cache import MAX_CACHED_PLAN_BYTES, ResolutionCache, world_key
from services.resolver.errors import ResolveError
from services.resolver.memory import ObjectMemory, Origin
from services.resolver.node import Perception, handler
from services.resolver.resolver import Resolver
from services.runtime import encode


def grounded(seconds: float) -> GroundedPlan:
    plan = Plan(steps=[Step(action=Action.WAIT, params={"duration": seconds})])
    return GroundedPlan(steps=[WaitStep(duration=seconds)], source=plan, labels=["1"])


def people(x: float, y: float = 1.5, yaw: float = 3.14) -> PerceivedHumans:
    return PerceivedHumans(
        stamp=1.0, humans=[PerceivedHuman(id="operator", name="operator", pose=Pose2D(x=x, y=y, yaw=yaw))]
    )


ROBOT = Pose2D(x=6.0, y=1.2, yaw=0.0)
WORLD = world_key(3, ROBOT, None)


def test_a_hit_for_the_same_plan_in_the_same_world() -> None:
    cache = ResolutionCache(8)
    plan = grounded(1.0)
    request = encode(plan.source)
    assert cache.get(WORLD, request) is None
    cache.put(WORLD, request, plan)
    assert cache.get(world_key(3, ROBOT, None), request) is plan
    assert cache.get(WORLD, encode(grounded(2.0).source)) is None
    assert (cache.hits, cache.misses) == (1, 2)


def test_refusals_are_never_kept() -> None:
    cache = ResolutionCache(8)
    cache.get(WORLD, b"plan")
    cache.put(WORLD, b"plan", ServiceError(kind=ErrorKind.UNKNOWN_NAME, message="unknown name 'cpu'"))
    assert cache.get(WORLD, b"plan") is None
    assert len(cache) == 0


def test_size_zero_disables_it() -> None:
    cache = ResolutionCache(0)
    cache.get(WORLD, b"plan")
    cache.put(WORLD, b"plan", grounded(1.0))
    assert cache.get(WORLD, b"plan") is None
    assert len(cache) == 0


def test_least_recently_used_goes_first() -> None:
    cache = ResolutionCache(2)
    cache.get(WORLD, b"a")
    cache.put(WORLD, b"a", grounded(1.0))
    cache.put(WORLD, b"b", grounded(2.0))
    assert cache.get(WORLD, b"a") is not None  # a is now the most recent
    cache.put(WORLD, b"c", grounded(3.0))
    assert len(cache) == 2
    assert cache.get(WORLD, b"b") is None
    assert cache.get(WORLD, b"a") is not None and cache.get(WORLD, b"c") is not None


def test_a_new_world_drops_every_entry() -> None:
    cache = ResolutionCache(8)
    cache.get(WORLD, b"a")
    cache.put(WORLD, b"a", grounded(1.0))
    assert cache.get(world_key(4, ROBOT, None), b"a") is None
    assert len(cache) == 0
    # Back to the old world: gone all the same.
    assert cache.get(WORLD, b"a") is None


def test_a_reply_from_an_overtaken_world_is_not_kept() -> None:
    cache = ResolutionCache(8)
    newer = world_key(4, ROBOT, None)
    cache.get(WORLD, b"slow")  # a query resolved in the old world...
    cache.get(newer, b"a")  # ...overtaken by one in the new world
    cache.put(newer, b"a", grounded(1.0))
    cache.put(WORLD, b"slow", grounded(2.0))
    assert cache.get(newer, b"a") is not None
    assert cache.get(newer, b"slow") is None


def test_big_plans_are_not_kept() -> None:
    cache = ResolutionCache(8)
    big = b"x" * (MAX_CACHED_PLAN_BYTES + 1)
    cache.get(WORLD, big)
    cache.put(WORLD, big, grounded(1.0))
    assert len(cache) == 0


@pytest.mark.parametrize(
    ("a", "b", "same"),
    [
        (Pose2D(x=6.0, y=1.2, yaw=0.0), Pose2D(x=6.003, y=1.198, yaw=0.002), True),  # odometry jitter
        (Pose2D(x=6.0, y=1.2, yaw=0.0), Pose2D(x=6.02, y=1.2, yaw=0.0), False),  # 2 cm
        (Pose2D(x=6.0, y=1.2, yaw=0.0), Pose2D(x=6.0, y=1.2, yaw=0.02), False),  # 0.02 rad
        (Pose2D(x=6.0, y=1.2, yaw=0.5), Pose2D(x=6.0, y=1.2, yaw=0.5 + 6.283185307179586), True),  # a full turn
    ],
)
def test_the_robot_pose_is_quantised(a: Pose2D, b: Pose2D, same: bool) -> None:
    assert (world_key(1, a, None) == world_key(1, b, None)) is same


def test_people_are_quantised_more_coarsely() -> None:
    assert world_key(1, ROBOT, people(9.5)) == world_key(1, ROBOT, people(9.51))
    assert world_key(1, ROBOT, people(9.5)) != world_key(1, ROBOT, people(9.6))
    assert world_key(1, ROBOT, people(9.5)) != world_key(1, ROBOT, None)
    assert world_key(1, None, None) != world_key(1, ROBOT, None)


def test_people_count_as_the_resolver_reads_them() -> None:
    # The last report of an id wins there, and the order of different people does not matter.
    one = PerceivedHuman(id="operator", name="operator", pose=Pose2D(x=1.0, y=1.0))
    moved = PerceivedHuman(id="operator", name="operator", pose=Pose2D(x=5.0, y=1.0))
    guest = PerceivedHuman(id="guest", name="guest", pose=Pose2D(x=2.0, y=2.0))
    assert world_key(1, None, PerceivedHumans(stamp=1.0, humans=[one, guest])) == world_key(
        1, None, PerceivedHumans(stamp=2.0, humans=[guest, one])
    )
    assert world_key(1, None, PerceivedHumans(stamp=1.0, humans=[one, moved])) == world_key(
        1, None, PerceivedHumans(stamp=1.0, humans=[moved])
    )


# The resolver service's handler goes through the cache with what it remembers.


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class FakeResolver:
    """Records what it was asked with; refuses a plan that says "cup", grounds any other as a wait."""

    def __init__(self) -> None:
        self.calls: list[tuple[Plan, PerceivedObjects | None, Pose2D | None, PerceivedHumans | None]] = []
        self.origins: list[dict[str, Origin]] = []

    def resolve(
        self,
        plan: Plan,
        objects: PerceivedObjects | None = None,
        robot: Pose2D | None = None,
        *,
        humans: PerceivedHumans | None = None,
        origins: Mapping[str, Origin] | None = None,
    ) -> GroundedPlan:
        self.calls.append((plan, objects, robot, humans))
        self.origins.append(dict(origins or {}))
        if plan.steps[0].target == "cup":
            raise ResolveError("'cup' is ambiguous", kind=ErrorKind.AMBIGUOUS_NAME)
        return GroundedPlan(steps=[WaitStep(duration=1.0)], source=plan, labels=["1"])


def pick(target: str) -> Plan:
    return Plan(steps=[Step(action=Action.PICK, target=target)])


def cup_at(x: float) -> PerceivedObjects:
    cup = PerceivedObject(id="blue_cup", name="blue cup", cls="cup", color="blue", position=Vec3(x=x, y=2.4, z=0.5))
    return PerceivedObjects(stamp=1.0, objects=[cup])


def test_the_handler_resolves_with_what_it_remembers() -> None:
    clock, fake = Clock(), FakeResolver()
    latest = Perception(ObjectMemory(stale_after=60.0, move_tolerance=0.05), clock)
    handle = handler(cast(Resolver, fake), latest, ResolutionCache(0))
    handle(pick("blue cup"))
    assert fake.calls[-1][1:] == (None, None, None)  # nothing perceived yet: the gripper is not known
    latest.on_objects(cup_at(8.2))
    latest.on_odom(Odometry(stamp=1.0, sim_time=1.0, pose=ROBOT, linear_x=0.0, angular_z=0.0))
    latest.on_humans(people(9.5))
    latest.on_objects(PerceivedObjects(stamp=2.0, objects=[]))  # the cup out of view: still remembered
    clock.now = 0.5
    handle(pick("blue cup"))
    assert fake.calls[-1][2] == ROBOT
    clock.now = 61.0
    handle(pick("blue cup"))
    _, objects, robot, humans = fake.calls[-1]
    assert objects is not None and [(o.id, o.position.x, o.stale) for o in objects.objects] == [("blue_cup", 8.2, True)]
    # Odometry a minute old is no pose (a drive relative to it is refused); people stay as last seen.
    assert robot is None and humans == people(9.5)


def test_odometry_counts_for_odom_max_age_after_it_arrived() -> None:
    """An hour-old pose grounded "drive 1 m forward" to an absolute goal from where the robot once stood."""
    clock, fake = Clock(), FakeResolver()
    latest = Perception(ObjectMemory(stale_after=60.0, move_tolerance=0.05), clock, odom_max_age=1.0)
    handle = handler(cast(Resolver, fake), latest, ResolutionCache(8))
    latest.on_odom(Odometry(stamp=1.0, sim_time=1.0, pose=ROBOT, linear_x=0.0, angular_z=0.0))
    clock.now = 1.0
    handle(pick("blue cup"))
    assert fake.calls[-1][2] == ROBOT
    clock.now = 1.01
    handle(pick("blue cup"))
    assert fake.calls[-1][2] is None, "and not the cached answer from when it was fresh"


def test_a_person_out_of_the_latest_report_stays_where_last_seen() -> None:
    """A people tracker lists whom it sees: the operator missing from one report went back to the
    world file's pose ("bring it to me" to the living room, the operator in the bedroom)."""
    fake = FakeResolver()
    latest = Perception(ObjectMemory(stale_after=60.0, move_tolerance=0.05), Clock())
    handle = handler(cast(Resolver, fake), latest, ResolutionCache(8))
    latest.on_humans(people(1.0, 7.5))
    guest = PerceivedHuman(id="guest", name="guest", pose=Pose2D(x=3.0, y=3.0, yaw=0.0))
    latest.on_humans(PerceivedHumans(stamp=2.0, humans=[guest]))
    handle(pick("blue cup"))
    humans = fake.calls[-1][3]
    assert humans is not None and humans.stamp == 2.0
    assert {h.id: (h.pose.x, h.pose.y) for h in humans.humans} == {"operator": (1.0, 7.5), "guest": (3.0, 3.0)}
    # One id at two poses in one report: which is meant is not known, so it is not moved.
    twice = people(9.0).humans + people(2.0).humans
    latest.on_humans(PerceivedHumans(stamp=3.0, humans=twice))
    handle(pick("blue cup"))
    humans = fake.calls[-1][3]
    assert humans is not None and {h.id: h.pose.x for h in humans.humans}["operator"] == 1.0


def test_perception_of_ids_the_world_does_not_know_pushes_out_no_real_object() -> None:
    """A frame of 1,000 made-up ids evicted the red cup the camera had seen; it fell back to the world file."""
    memory = ObjectMemory(stale_after=60.0, move_tolerance=0.05, known={"blue_cup"})
    memory.update(cup_at(8.2), 0.0)
    made_up = [
        PerceivedObject(id=f"thing_{i}", name="thing", cls="thing", color="grey", position=Vec3(x=1.0, y=1.0, z=0.0))
        for i in range(1000)
    ]
    memory.update(PerceivedObjects(stamp=2.0, objects=made_up), 1.0)
    snapshot = memory.snapshot(2.0)
    assert snapshot is not None and [(o.id, o.position.x) for o in snapshot.objects] == [("blue_cup", 8.2)]


def test_the_handler_tells_the_resolver_where_a_held_object_was_before() -> None:
    fake = FakeResolver()
    latest = Perception(ObjectMemory(stale_after=60.0, move_tolerance=0.05), Clock())
    handle = handler(cast(Resolver, fake), latest, ResolutionCache(8))
    on_table = cup_at(8.2).objects[0]
    latest.on_objects(PerceivedObjects(stamp=1.0, objects=[msgspec.structs.replace(on_table, on="coffee_table")]))
    handle(pick("blue cup"))
    assert fake.origins[-1] == {}  # not held: nothing to put back
    lifted = msgspec.structs.replace(on_table, on="gripper", position=Vec3(x=7.9, y=1.9, z=1.0))
    latest.on_objects(PerceivedObjects(stamp=2.0, objects=[lifted]))
    handle(pick("blue cup"))
    assert fake.origins[-1] == {"blue_cup": Origin("coffee_table", on_table.position)}


def test_the_handler_answers_repeats_from_the_cache_until_the_world_changes(caplog: pytest.LogCaptureFixture) -> None:
    fake = FakeResolver()
    latest = Perception(ObjectMemory(stale_after=60.0, move_tolerance=0.05), Clock())
    handle = handler(cast(Resolver, fake), latest, ResolutionCache(8))
    caplog.set_level(logging.DEBUG, logger="services.resolver.node")
    first = handle(pick("blue cup"))
    assert isinstance(first, GroundedPlan)
    assert handle(pick("blue cup")) is first
    assert len(fake.calls) == 1
    assert any("from the cache" in r.getMessage() and r.levelno == logging.DEBUG for r in caplog.records)
    latest.on_objects(cup_at(8.2))  # perception: a new world
    assert handle(pick("blue cup")) is not first
    latest.on_objects(cup_at(8.201))  # noise: the same world
    handle(pick("blue cup"))
    assert len(fake.calls) == 2


def test_the_handler_does_not_keep_refusals() -> None:
    fake, cache = FakeResolver(), ResolutionCache(8)
    handle = handler(cast(Resolver, fake), Perception(ObjectMemory(stale_after=60.0, move_tolerance=0.05)), cache)
    for _ in range(2):
        reply = handle(pick("cup"))
        assert isinstance(reply, ServiceError) and reply.kind is ErrorKind.AMBIGUOUS_NAME
    assert len(fake.calls) == 2 and len(cache) == 0
