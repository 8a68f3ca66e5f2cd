"""The resolver's perception against a hostile or broken robot: what it remembers of people, with the
service's own wiring (declare) on a stand-in node and the household world."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from schemas import keys
from schemas.common import Pose2D
from schemas.plan import Action, GroundedPlan, NavigateStep, Plan, Step
from schemas.world import Empty, PerceivedHuman, PerceivedHumans, SceneDescription
from services.resolver.config import ResolverConfig
from services.resolver.node import MAX_PEOPLE, build_resolver, declare

BEDROOM = Pose2D(x=2.0, y=7.0, yaw=0.0)


class StandInNode:
    """What declare() touches of a Node: the subscriptions' callbacks and the handlers, by key."""

    def __init__(self) -> None:
        self.callbacks: dict[Any, Callable[[Any], None]] = {}
        self.handlers: dict[Any, Callable[[Any], Any]] = {}

    def subscribe(self, topic: Any, callback: Callable[[Any], None]) -> None:
        self.callbacks[topic] = callback

    def serve(self, service: Any, handler: Callable[[Any], Any], **_: Any) -> None:
        self.handlers[service] = handler


def person(person_id: str, pose: Pose2D) -> PerceivedHuman:
    return PerceivedHuman(id=person_id, name="person", pose=pose)


def test_made_up_people_push_out_no_person_of_the_world() -> None:
    """A people tracker (or a hostile peer) reporting more than MAX_PEOPLE ids the world does not know
    pushed the operator out of what the resolver remembered: "come to me" then drove to where the world
    file puts the operator (the living room), not to the bedroom where they were last seen."""
    node = StandInNode()
    declare(node, build_resolver(ResolverConfig()), ResolverConfig())  # type: ignore[arg-type]
    on_humans = node.callbacks[keys.HUMANS]
    on_humans(PerceivedHumans(stamp=1.0, humans=[person("operator", BEDROOM)]))
    strangers = [person(f"track_{n}", Pose2D(x=8.5, y=2.5, yaw=0.0)) for n in range(MAX_PEOPLE + 1)]
    on_humans(PerceivedHumans(stamp=2.0, humans=strangers))

    scene: SceneDescription = node.handlers[keys.SCENE](Empty())
    assert "The operator is in the bedroom" in scene.text, scene.text
    grounded = node.handlers[keys.PLAN_RESOLVE](Plan(steps=[Step(action=Action.NAVIGATE_TO, target="me")]))
    assert isinstance(grounded, GroundedPlan), grounded
    [goal] = grounded.steps
    assert isinstance(goal, NavigateStep) and goal.goal.y > 5.0, goal


def test_a_person_reported_off_the_map_is_not_believed() -> None:
    """Objects are checked against the map before they are believed; people were not: a tracker
    reporting the operator at (900, 900) had "come to me" grounded as a goal 1.2 km off the map."""
    node = StandInNode()
    declare(node, build_resolver(ResolverConfig()), ResolverConfig())  # type: ignore[arg-type]
    node.callbacks[keys.HUMANS](PerceivedHumans(stamp=1.0, humans=[person("operator", Pose2D(x=900.0, y=900.0))]))

    grounded = node.handlers[keys.PLAN_RESOLVE](Plan(steps=[Step(action=Action.NAVIGATE_TO, target="me")]))
    assert isinstance(grounded, GroundedPlan), grounded
    [goal] = grounded.steps
    # Where the world file puts the operator (9.5, 1.5): as if the tracker had not seen them.
    assert isinstance(goal, NavigateStep) and abs(goal.goal.x - 9.5) < 1.0 and abs(goal.goal.y - 1.5) < 1.0, goal
    assert any("operator is not believed" in w and "off the map" in w for w in grounded.warnings), grounded.warnings
    scene: SceneDescription = node.handlers[keys.SCENE](Empty())
    assert "The operator is in the living room" in scene.text, scene.text
