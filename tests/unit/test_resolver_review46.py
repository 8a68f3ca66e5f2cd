"""Review 46 of the resolver: parameters the vocabulary takes and nothing carries out are not dropped unsaid."""

from __future__ import annotations

from schemas.common import Pose2D
from services.parser.parser import parse
from services.resolver.resolver import UNUSED_PARAMS, Resolver
from tests.unit.test_resolver import model as model  # the fixtures, shared
from tests.unit.test_resolver import resolver as resolver
from tests.unit.test_resolver import seen


def test_each_parameter_nothing_carries_out_is_named_in_the_warnings(resolver: Resolver) -> None:
    # Before, approach, width, force and volume were read and bounds-checked, then dropped with no
    # warning, while the agent's tools told the model what each would do.
    plan = parse(
        '{"plan": ['
        '{"action": "pick", "target": "red cup", "parameters": {"approach": "side"}},'
        '{"action": "place", "target": "coffee table", "parameters": {"approach": "top"}},'
        '{"action": "open_gripper", "parameters": {"width": 0.04}},'
        '{"action": "close_gripper", "parameters": {"force": 20}},'
        '{"action": "say", "parameters": {"text": "done", "volume": 0.5}}'
        "]}",
        "json",
    )
    grounded = resolver.resolve(plan, seen(resolver.model), Pose2D(x=6.0, y=1.2))
    expected = [
        "step 1: parameter 'approach' is not used: the executor chooses the grasp",
        "step 2: parameter 'approach' is not used: the executor chooses how the hand comes down",
        "step 3: parameter 'width' is not used: the gripper opens fully",
        "step 4: parameter 'force' is not used: the gripper closes with its own force",
        "step 5: parameter 'volume' is not used: this robot has no speaker",
    ]
    assert [w for w in grounded.warnings if "is not used" in w] == expected, grounded.warnings
    assert len(UNUSED_PARAMS) == len(expected)


def test_a_plan_without_them_has_no_such_warning(resolver: Resolver) -> None:
    plan = parse('{"plan": [{"action": "open_gripper"}, {"action": "say", "parameters": {"text": "hi"}}]}', "json")
    grounded = resolver.resolve(plan, seen(resolver.model), Pose2D(x=6.0, y=1.2))
    assert not [w for w in grounded.warnings if "is not used" in w], grounded.warnings
