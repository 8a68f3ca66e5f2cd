"""The resolver's reference corpus: every case resolves as it says; the runner checks the cases themselves."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from schemas.common import ErrorKind, Pose2D, ServiceError
from schemas.plan import GroundedPlan, Plan, Resolution, Step, StopStep
from services.resolver.resolver import Resolver
from services.worldmodel import load_world
from tests.corpus.resolver.runner import Case, CorpusError, case_id, check, default_resolver, load_raw, parse_case

MIN_CASES = 50
RAW = load_raw()
WORLD = load_world("household")


@pytest.fixture(scope="module")
def resolver() -> Resolver:
    return default_resolver()


@pytest.mark.parametrize(("index", "raw"), list(enumerate(RAW)), ids=[case_id(i, r) for i, r in enumerate(RAW)])
def test_reference(index: int, raw: Any, resolver: Resolver) -> None:
    from tests.corpus.resolver.runner import run_case

    outcome = run_case(parse_case(index, raw, resolver.world), resolver)
    assert outcome.passed, outcome.detail


def test_corpus_has_enough_cases() -> None:
    assert len(RAW) >= MIN_CASES


# The runner itself, on replies made up here (independent of what the resolver does today).


def case(**fields: Any) -> Case:
    return parse_case(7, {"ref": "red cup", "expect": {"id": "red_cup"}} | fields, WORLD)


def grounded(*resolutions: Resolution, warnings: tuple[str, ...] = ()) -> GroundedPlan:
    return GroundedPlan(
        steps=[StopStep()],
        source=Plan(steps=[Step()]),
        labels=["1"],
        resolutions=list(resolutions),
        warnings=list(warnings),
    )


def test_a_case_becomes_a_plan_with_its_inputs() -> None:
    built = case(
        ref="coffee table",
        action="place",
        field="location",
        target="it",
        before=[{"action": "pick", "target": "red cup"}],
        seen={"red_cup": {"position": [2.2, 0.55, 0.95], "on": "gripper"}},
        humans={"operator": {"x": 1.0, "y": 2.0}},
    )
    assert built.label == "2"
    assert [(s.action, s.target, s.location) for s in built.plan.steps] == [
        ("pick", "red cup", None),
        ("place", "it", "coffee table"),
    ]
    assert built.robot == WORLD.robot.start
    assert built.objects is not None
    (cup,) = built.objects.objects
    assert (cup.name, cup.cls, cup.color, cup.on, cup.stale) == ("red cup", "cup", "red", "gripper", False)
    assert built.humans is not None and built.humans.humans[0].name == "operator"


def test_robot_null_means_not_known_and_no_seen_means_nothing_perceived() -> None:
    built = case(robot=None)
    assert built.robot is None and built.objects is None and built.humans is None
    assert case(robot={"x": 1.0, "y": 2.0, "yaw": 0.5}).robot == Pose2D(x=1.0, y=2.0, yaw=0.5)
    empty = case(seen={}).objects
    assert empty is not None and empty.objects == []


@pytest.mark.parametrize(
    ("fields", "complaint"),
    [
        ({"refs": "cup"}, "unknown field `refs`"),
        ({"action": "fly"}, "$.action"),
        ({"before": [{"action": "teleport"}]}, "$.before[0].action"),
        ({"field": "where"}, "$.field"),
        ({"target": "cup"}, "'target' is the ref itself"),
        ({"expect": {"id": "red_cup", "refused": "unknown_name"}}, "mean nothing for a refusal"),
        ({"expect": {"id": "red_cup", "candidates": ["a"]}}, "only go with 'refused'"),
        ({"expect": {"via": "name"}}, "needs 'id' or 'kind'"),
        ({"expect": {"refused": "confused"}}, "$.expect.refused"),
        ({"expect": {"id": "red_cup", "kind": "thing"}}, "$.expect.kind"),
        ({"seen": {"unicorn": {"position": [1, 1, 1]}}}, "'unicorn' is not an object"),
        ({"seen": {"red_cup": {"position": [1, 1]}}}, "length >= 3 - at `$.seen[...].position`"),
        ({"humans": {"burglar": {"x": 1, "y": 1}}}, "'burglar' is not a person"),
    ],
)
def test_a_malformed_case_fails_loudly_naming_it(fields: dict[str, Any], complaint: str) -> None:
    with pytest.raises(CorpusError) as caught:
        case(**fields)
    assert str(caught.value).startswith("case 7 ('red cup'): ")
    assert complaint in str(caught.value)


def test_on_is_a_key_not_a_boolean(tmp_path: Path) -> None:
    # YAML 1.1 reads `on`, `yes` and `no` as booleans; the corpus writes `on: coffee_table`.
    path = tmp_path / "references.yaml"
    path.write_text("- {ref: yes, seen: {red_cup: {position: [1, 2, 3], on: coffee_table, stale: true}}}\n")
    (raw,) = load_raw(path)
    assert raw == {"ref": "yes", "seen": {"red_cup": {"position": [1, 2, 3], "on": "coffee_table", "stale": True}}}


def test_a_case_that_is_not_a_mapping_is_named() -> None:
    with pytest.raises(CorpusError, match=r"^case 3: "):
        parse_case(3, ["ref", "cup"], WORLD)


def resolution(text: str = "red cup", label: str = "1", **fields: Any) -> Resolution:
    values: dict[str, Any] = {"kind": "object", "name": "red cup", "id": "red_cup", "via": "name"} | fields
    return Resolution(label=label, text=text, **values)


def test_a_resolution_is_found_by_label_and_text() -> None:
    expect = {"id": "red_cup", "kind": "object", "via": "name", "warning": "NOT SEEN"}
    assert check(case(expect=expect), grounded(resolution(), warnings=("red cup not seen for 70 s",))).passed
    wrong = check(case(expect=expect), grounded(resolution(id="blue_cup", via="fuzzy")))
    assert not wrong.passed
    assert "id: expected 'red_cup', got 'blue_cup'" in wrong.detail and "via: expected 'name'" in wrong.detail
    assert "no warning contains 'NOT SEEN'" in wrong.detail
    elsewhere = check(case(), grounded(resolution(label="2"), resolution(text="cup")))
    assert not elsewhere.passed and "no resolution of 'red cup' at step 1" in elsewhere.detail
    refused = check(case(), ServiceError(kind=ErrorKind.UNKNOWN_NAME, message="unknown name 'red cup'"))
    assert not refused.passed and "got a refusal" in refused.detail


def test_a_refusal_is_checked_for_kind_step_candidates_and_message() -> None:
    expected = case(
        ref="cup", expect={"refused": "ambiguous_name", "candidates": ["red cup", "blue cup"], "message": "Ambiguous"}
    )
    error = ServiceError(
        kind=ErrorKind.AMBIGUOUS_NAME, message="'cup' is ambiguous", step=0, candidates=["blue cup", "red cup"]
    )
    assert check(expected, error).passed
    assert not check(expected, grounded(resolution(text="cup"))).passed
    wrong = ServiceError(kind=ErrorKind.UNKNOWN_NAME, message="no", step=1, candidates=["red cup"])
    detail = check(expected, wrong).detail
    for part in ("kind: expected ambiguous_name", "refused at step 2, not step 1", "candidates:", "message does not"):
        assert part in detail


def test_a_resolver_that_raises_fails_the_case_with_its_traceback() -> None:
    from tests.corpus.resolver.runner import run_case

    class Broken(Resolver):
        def __init__(self) -> None:
            pass

        def resolve(self, *args: Any, **kwargs: Any) -> GroundedPlan:
            raise KeyError("boom")

    outcome = run_case(case(), Broken())
    assert not outcome.passed and "KeyError: 'boom'" in outcome.detail
