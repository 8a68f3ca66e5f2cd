"""Where the resolver believes a person is after a report it does not believe: where they were last
believably seen, with the service's own wiring (declare) on a stand-in node and the household world."""

from __future__ import annotations

from schemas import keys
from schemas.common import Pose2D
from schemas.plan import Action, GroundedPlan, NavigateStep, Plan, Step
from schemas.world import Empty, PerceivedHumans, SceneDescription
from services.resolver.config import ResolverConfig
from services.resolver.node import build_resolver, declare
from tests.unit.test_resolver_races import BEDROOM, StandInNode, person

COME_TO_ME = Plan(steps=[Step(action=Action.NAVIGATE_TO, target="me")])
OFF_THE_MAP = Pose2D(x=900.0, y=900.0)
KITCHEN = Pose2D(x=2.5, y=2.5)


def wired() -> StandInNode:
    node = StandInNode()
    declare(node, build_resolver(ResolverConfig()), ResolverConfig())  # type: ignore[arg-type]
    return node


def report(node: StandInNode, stamp: float, pose: Pose2D) -> None:
    node.callbacks[keys.HUMANS](PerceivedHumans(stamp=stamp, humans=[person("operator", pose)]))


def come_to_me(node: StandInNode) -> GroundedPlan:
    grounded = node.handlers[keys.PLAN_RESOLVE](COME_TO_ME)
    assert isinstance(grounded, GroundedPlan), grounded
    return grounded


def test_after_a_report_off_the_map_the_operator_is_where_last_believably_seen() -> None:
    """The operator seen in the bedroom, then reported at (900, 900): the report was not believed, but
    it was kept as where they were last seen, so "come to me" drove to where the world file puts them
    (the living room)."""
    node = wired()
    report(node, 1.0, BEDROOM)
    report(node, 2.0, OFF_THE_MAP)

    grounded = come_to_me(node)
    [goal] = grounded.steps
    assert isinstance(goal, NavigateStep) and goal.goal.y > 5.0, goal
    assert any("operator is not believed" in w and "off the map" in w for w in grounded.warnings), grounded.warnings
    scene: SceneDescription = node.handlers[keys.SCENE](Empty())
    assert "The operator is in the bedroom" in scene.text, scene.text


def test_each_answer_follows_the_believed_pose_and_the_doubted_report_the_caches_too() -> None:
    """The cache reads one pose per id: a plan grounded with the operator in the bedroom must not be
    served once they were seen in the kitchen (whatever came off the map since), nor a plan warning
    of a report off the map once a believable one came."""
    node = wired()
    report(node, 1.0, BEDROOM)
    report(node, 2.0, OFF_THE_MAP)
    first = come_to_me(node)
    assert first.steps[0].goal.y > 5.0 and first.warnings  # type: ignore[union-attr]

    report(node, 3.0, KITCHEN)
    report(node, 4.0, OFF_THE_MAP)
    grounded = come_to_me(node)
    [goal] = grounded.steps
    assert isinstance(goal, NavigateStep) and goal.goal.x < 5.0 and goal.goal.y < 5.0, goal
    assert any("operator is not believed" in w for w in grounded.warnings), grounded.warnings

    report(node, 5.0, KITCHEN)
    again = come_to_me(node)
    assert again.steps == grounded.steps
    assert not any("not believed" in w for w in again.warnings), again.warnings
