"""Every kind of grounded step and every action is handled wherever code dispatches on them."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any, ClassVar, get_args

import msgspec
import pytest

from schemas.common import Frozen, Pose2D, Vec3
from schemas.plan import (
    STEP_TYPES,
    Action,
    DetectStep,
    GripperStep,
    GroundedPlan,
    GroundedStep,
    NavigateStep,
    PickStep,
    PlaceStep,
    Plan,
    SayStep,
    Step,
    StepSpec,
    StopStep,
    WaitStep,
    step_kind,
)
from schemas.robot import GripperCommandGoal, Twist
from services.agent.tools import REFUSED, all_tools
from services.executor.config import ExecutorConfig
from services.executor.manipulation import GRIPPER_OPEN, Manipulator
from services.parser.errors import VocabularyError
from services.parser.parser import parse
from services.parser.vocabulary import load_vocabulary
from services.resolver.errors import ResolveError
from services.resolver.resolver import Resolver
from services.robotmodel import ArmModel
from services.safety.errors import Vetoed
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel, load_world
from tests.unit.test_runner import WORLD, ScriptedRobot, planners

COUNTER = Pose2D(x=2.5, y=1.05, yaw=-1.57)
START = Pose2D(x=6.0, y=1.2)
SOURCE = Plan(steps=[Step(action=Action.STOP)])

# One small, valid step of each kind, as the resolver would ground it in the household world.
EXAMPLES: dict[type[Any], GroundedStep] = {
    NavigateStep: NavigateStep(target="kitchen counter", goal=COUNTER),
    PickStep: PickStep(
        object_id="red_cup",
        object_name="red cup",
        position=Vec3(x=2.2, y=0.55, z=0.95),
        mass=0.25,
        support_id="kitchen_counter",
        approach=COUNTER,
    ),
    PlaceStep: PlaceStep(
        surface_id="kitchen_counter",
        surface_name="kitchen counter",
        position=Vec3(x=2.2, y=0.55, z=0.95),
        approach=COUNTER,
    ),
    DetectStep: DetectStep(object_id="red_cup", object_name="red cup"),
    SayStep: SayStep(text="hello"),
    WaitStep: WaitStep(duration=0.0),
    StopStep: StopStep(),
    GripperStep: GripperStep(open=False),
}
KINDS = [pytest.param(EXAMPLES.get(t), id=step_kind(t)) for t in STEP_TYPES]


class TeleportStep(Frozen, tag="teleport"):
    """A moving kind that is not in GroundedStep: what a new action looks like before it is wired in."""

    spec: ClassVar[StepSpec] = StepSpec(moves_base=True, timeout=10.0, retries=0)

    goal: Pose2D


FOREIGN: Any = TeleportStep(goal=Pose2D(x=11.2, y=8.0))


class TwistRecordingRobot(ScriptedRobot):
    """A ScriptedRobot that keeps every twist it is sent."""

    def __init__(self) -> None:
        super().__init__()
        self.twists: list[Twist] = []

    def cmd_vel(self, twist: Twist) -> None:
        self.twists.append(twist)


class RecordingManipulator(Manipulator):
    """Manipulator.run's dispatch over motions that each succeed at once, recorded by name."""

    def __init__(self) -> None:
        self.recording_robot = TwistRecordingRobot()
        self.robot = self.recording_robot
        self.calls: list[str] = []

    def _did(self, name: str) -> str:
        self.calls.append(name)
        return name

    def drive_to(self, goal: Pose2D, cancel: threading.Event, max_speed: float | None, attempt: int = 1) -> None:
        self._did("drive_to")

    def operate_gripper(self, open_: bool, cancel: threading.Event) -> str:
        return self._did("operate_gripper")

    def pick(self, step: PickStep, cancel: threading.Event, attempt: int, note: Any, searched: Any = None) -> str:
        return self._did("pick")

    def place(self, step: PlaceStep, cancel: threading.Event, attempt: int, note: Any) -> str:
        return self._did("place")

    def detect(self, step: DetectStep, cancel: threading.Event, attempt: int, note: Any, searched: Any = None) -> str:
        return self._did("detect")


@pytest.fixture(scope="module")
def policy() -> SafetyPolicy:
    world = load_world()
    arm = ArmModel(world.robot.arm_urdf)
    return SafetyPolicy(WorldModel(world), load_policy(None, world.robot, arm, world.keep_out), arm)


@pytest.fixture(scope="module")
def manipulator() -> Manipulator:
    arm, base = planners()
    return Manipulator(ScriptedRobot(), arm, base, WORLD, ExecutorConfig())


@pytest.fixture(scope="module")
def resolver() -> Resolver:
    return Resolver(WORLD)


def check(policy: SafetyPolicy, step: Any, start: Pose2D | None) -> list[str] | Vetoed:
    """What safety's plan check says of a plan of this one step: its checks, or its veto."""
    try:
        return policy.check_plan(GroundedPlan(steps=[step], source=SOURCE), start)
    except Vetoed as exc:
        return exc


def test_the_examples_cover_every_kind_and_every_kind_declares_a_spec() -> None:
    assert get_args(GroundedStep) == STEP_TYPES
    assert set(EXAMPLES) == set(STEP_TYPES), "add a small example of the new kind to EXAMPLES"
    assert len({step_kind(t) for t in STEP_TYPES}) == len(STEP_TYPES)
    for kind in STEP_TYPES:
        assert isinstance(kind.spec, StepSpec), step_kind(kind)
        assert "spec" not in kind.__struct_fields__


@pytest.mark.parametrize("step", KINDS)
def test_every_kind_has_a_timeout_and_retries_defaulting_to_its_spec(step: GroundedStep) -> None:
    config = ExecutorConfig()
    assert config.timeouts.of(step) == step.spec.timeout
    assert config.retries.of(step) == step.spec.retries
    table = msgspec.convert({"timeouts": {step_kind(step): 7.5}, "retries": {step_kind(step): 3}}, ExecutorConfig)
    assert (table.timeouts.of(step), table.retries.of(step)) == (7.5, 3)


def test_the_step_tables_keep_their_keys_and_defaults_and_refuse_unknown_keys() -> None:
    config = ExecutorConfig()
    assert msgspec.structs.asdict(config.timeouts) == {
        "navigate_to": 300.0,
        "pick": 240.0,
        "place": 240.0,
        "detect": 240.0,
        "gripper": 30.0,
        "say": 10.0,
        "wait": 120.0,
        "stop": 10.0,
    }
    assert msgspec.structs.asdict(config.retries) == {
        "navigate_to": 2,
        "pick": 2,
        "place": 2,
        "detect": 1,
        "gripper": 0,
        "say": 0,
        "wait": 0,
        "stop": 0,
    }
    with pytest.raises(msgspec.ValidationError, match=r"unknown field `teleport` - at `\$.timeouts`"):
        msgspec.convert({"timeouts": {"teleport": 1.0}}, ExecutorConfig)
    with pytest.raises(msgspec.ValidationError, match=r"Expected `int` <= 10 - at `\$.retries.pick`"):
        msgspec.convert({"retries": {"pick": 11}}, ExecutorConfig)


@pytest.mark.parametrize("step", KINDS)
def test_every_kind_says_what_it_does_for_feedback_and_the_timeline(step: GroundedStep) -> None:
    assert step.describe()
    assert step.brief().startswith(step_kind(step)) or isinstance(step, GripperStep)


# What Manipulator.run calls for each kind (say, wait and stop are done in run itself).
RUN_CALLS: dict[type[Any], list[str]] = {
    NavigateStep: ["drive_to"],
    PickStep: ["pick"],
    PlaceStep: ["place"],
    DetectStep: ["detect"],
    SayStep: [],
    WaitStep: [],
    StopStep: [],
    GripperStep: ["operate_gripper"],
}


@pytest.mark.parametrize("step", KINDS)
def test_every_kind_is_run_by_the_manipulator(step: GroundedStep) -> None:
    assert set(RUN_CALLS) == set(STEP_TYPES), "say what running the new kind calls in RUN_CALLS"
    manipulator = RecordingManipulator()
    assert manipulator.run(step, threading.Event(), 1, lambda _: None)
    assert manipulator.calls == RUN_CALLS[type(step)]
    stopped = [Twist()] if isinstance(step, StopStep) else []
    assert manipulator.recording_robot.twists == stopped, "only a stop sends a twist: a zero one"


@pytest.mark.parametrize("step", KINDS)
def test_only_a_pick_opens_an_empty_hand_before_a_retry(step: GroundedStep) -> None:
    robot = ScriptedRobot()  # a fresh one for each kind: its gripper goals are this kind's alone
    arm, base = planners()
    Manipulator(robot, arm, base, WORLD, ExecutorConfig()).recover(step, threading.Event())
    opened = [GripperCommandGoal(position=GRIPPER_OPEN)] if isinstance(step, PickStep) else []
    assert robot.grips == opened
    assert robot.goals == [], "a way back drives nowhere"


@pytest.mark.parametrize("step", KINDS)
def test_safety_decides_on_every_kind_and_refuses_a_moving_one_without_a_pose(
    step: GroundedStep, policy: SafetyPolicy
) -> None:
    assert isinstance(check(policy, step, START), list)
    blind = check(policy, step, None)
    if step.spec.moves_base:
        assert isinstance(blind, Vetoed) and "pose is unknown" in str(blind)
    else:
        assert isinstance(blind, list)


def test_safety_never_approves_a_kind_it_has_no_case_for(policy: SafetyPolicy) -> None:
    # Before the match, _check_step ended in `return state`: this plan was approved unchecked.
    with pytest.raises(AssertionError, match="TeleportStep"):
        policy.check_plan(GroundedPlan(steps=[FOREIGN], source=SOURCE), START)
    with pytest.raises(AssertionError, match="TeleportStep"):
        policy.check_plan(GroundedPlan(steps=[EXAMPLES[SayStep], FOREIGN], source=SOURCE), START)


def test_no_dispatcher_passes_over_a_kind_it_has_no_case_for(manipulator: Manipulator) -> None:
    for dispatch in (
        lambda s: RecordingManipulator().run(s, threading.Event(), 1, lambda _: None),
        lambda s: manipulator.recover(s, threading.Event()),
    ):
        with pytest.raises(AssertionError, match="TeleportStep"):
            dispatch(FOREIGN)


@pytest.mark.parametrize("action", list(Action), ids=str)
def test_the_resolver_grounds_or_refuses_every_action(action: Action, resolver: Resolver) -> None:
    try:
        grounded = resolver.resolve(Plan(steps=[Step(action=action, target="kitchen counter")]), robot=START)
    except ResolveError as exc:
        assert str(exc)
    else:
        assert grounded.steps


def test_every_action_is_offered_as_a_tool_with_its_summary_or_refused() -> None:
    vocabulary = load_vocabulary()
    tools = {t.name: t for t in all_tools(vocabulary)}
    for action in Action:
        if action in REFUSED:
            assert action.value not in tools
        else:
            assert tools[action.value].description.startswith(vocabulary.actions[action].summary)


def test_an_action_without_a_summary_is_refused_when_the_vocabulary_loads(tmp_path: Path) -> None:
    vocabulary = msgspec.to_builtins(load_vocabulary())
    del vocabulary["actions"]["stop"]["summary"]
    path = tmp_path / "vocabulary.yaml"
    path.write_text(json.dumps(vocabulary))
    with pytest.raises(VocabularyError, match=r"no summary for actions \['stop'\]"):
        load_vocabulary(path)


NAMED = [a for a, spec in load_vocabulary().actions.items() if spec.names and a not in REFUSED]


@pytest.mark.parametrize("action", NAMED, ids=str)
def test_the_parser_reads_every_name_an_action_tool_offers(action: Action) -> None:
    names = load_vocabulary().actions[action].names
    arguments = {name: f"the {name}" for name in names}
    plan = parse(json.dumps([{"action": action.value, **arguments}]), "json")
    assert not [w for w in plan.warnings if "does not use it" in w]
    assert set(arguments.values()) <= {plan.steps[0].target, plan.steps[0].location}
