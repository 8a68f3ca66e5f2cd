"""Executor configuration: timeouts and retries per step, how busy goals are handled, how the arm moves."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, Any, Generic, Literal, TypeVar, get_args

import msgspec
from msgspec import Meta

from schemas.plan import STEP_TYPES, GroundedStep, SearchScope, StepSpec, step_kind

Timeout = Annotated[float, Meta(gt=0.0, le=3600.0)]
Retries = Annotated[int, Meta(ge=0, le=10)]
T = TypeVar("T")


class _PerStep(msgspec.Struct, Generic[T], frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A table with one key per kind of grounded step (its tag), defaults from the kind's spec."""

    def of(self, step: GroundedStep) -> T:
        value: T = getattr(self, step_kind(step))
        return value


def _per_step(name: str, type_: Any, default: Callable[[StepSpec], Any], doc: str) -> Any:
    fields = [(step_kind(cls), type_, default(cls.spec)) for cls in STEP_TYPES]
    return msgspec.defstruct(name, fields, bases=(_PerStep,), module=__name__, namespace={"__doc__": doc})


# Built at import with one field per step kind; mypy, which cannot follow defstruct, sees the base.
if TYPE_CHECKING:
    StepTimeouts = _PerStep[float]
    StepRetries = _PerStep[int]
else:
    StepTimeouts = _per_step(
        "StepTimeouts",
        Timeout,
        lambda spec: spec.timeout,
        """`[executor.timeouts]`: seconds one step may take, counted in motion time: while safety
    pauses the robot for a person nearby the clock stands still, and while it slows the robot the
    clock runs as much slower. A step over its time is canceled and fails (execution). One key per
    kind of step; defaults from its `spec` (schemas/plan.py).""",
    )
    StepRetries = _per_step(
        "StepRetries",
        Retries,
        lambda spec: spec.retries,
        """`[executor.retries]`: how often a step is tried again after a planning, execution or
    postcondition failure, each time after re-detecting what it acts on and planning anew. Never
    after a cancel, a veto or an e-stop. One key per kind of step; defaults from its `spec`.""",
    )


# How far a search for an object not in view may go: not at all, the furniture tops of the room the
# robot is in, or every furniture top of the flat. Narrowest first.
SEARCH_SCOPES: tuple[SearchScope, ...] = get_args(SearchScope)


class SearchConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """`[executor.search]`: how a detect or a pick looks for an object that is not in view. First
    it turns in place and looks (`headings` directions round the circle; from the room's centre pose
    when the base has no room to turn where it stands), then it visits the furniture tops of the
    room it is in, where memory last saw the object first, then, with `scope = "flat"`, those of the
    other rooms, nearest first. A place is the look around or one furniture top; `max_places` and
    `max_time` (wall seconds, checked before each move) bound the search, and a step's own `search`
    parameter may narrow `scope`, never widen it. The step's time (`[executor.timeouts]`) bounds it
    too. Not found within the bounds: the step fails naming every place it looked."""

    scope: SearchScope = "flat"
    max_places: Annotated[int, Meta(ge=0, le=50)] = 8
    max_time: Annotated[float, Meta(gt=0.0, le=3600.0)] = 120.0
    headings: Annotated[int, Meta(ge=2, le=12)] = 4
    # Metres of a furniture top's edge one look from its approach pose takes in; a longer top is
    # also looked at from along its edge towards each end (the counter, 2 m, from three poses).
    surface_view: Annotated[float, Meta(gt=0.1, le=10.0)] = 1.2


class ExecutorConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    world: str = "household"
    parse_timeout: Timeout = 5.0
    resolve_timeout: Timeout = 5.0
    check_timeout: Timeout = 5.0
    timeouts: StepTimeouts = StepTimeouts()
    retries: StepRetries = StepRetries()
    # A plan sent while another runs: rejected, or the running one canceled first (a goal's own
    # `preempt` asks for that too; `tether send --preempt`).
    when_busy: Literal["reject", "preempt"] = "reject"
    # Below the safety limit, so planned trajectories pass its check with margin.
    max_joint_speed: Annotated[float, Meta(gt=0.0, le=3.0)] = 1.0
    max_joint_acceleration: Annotated[float, Meta(gt=0.0, le=20.0)] = 3.0
    # Seconds one planning query (a base path, an arm path) may search before it gives up.
    planning_time: Annotated[float, Meta(gt=0.0, le=30.0)] = 1.0
    # How far the base's footprint keeps from walls and furniture on planned paths (metres): more
    # than the robot's tracking tolerance (services/footprint.py, 3 cm), which safety demands.
    base_clearance: Annotated[float, Meta(ge=0.0, le=0.5)] = 0.04
    # The base counts as at a pose within these (metres, radians): at an approach pose already (no
    # drive), and arrived after a navigation the robot reports succeeded (odometry must agree, or the
    # step fails, postcondition). Looser than the robot's own arrival (5 cm, 0.05 rad: docs/robot.md).
    approach_tolerance: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.15
    approach_yaw_tolerance: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.2
    # Heights above the grasp point: where the hand waits before descending, and lifts to after.
    pregrasp_height: Annotated[float, Meta(ge=0.0, le=0.5)] = 0.15
    place_clearance: Annotated[float, Meta(ge=0.0, le=0.2)] = 0.02
    # How far below an object's top the fingertips close at most; objects up to twice this tall
    # are held at their centre. The palm sits about 4 cm above the fingertips: grasping a 10 cm
    # cup at its centre pressed the palm onto its rim and tipped it over between the fingers.
    grasp_depth: Annotated[float, Meta(gt=0.0, le=0.2)] = 0.03
    search: SearchConfig = SearchConfig()
    # Seconds a motion may go on after its cancel before the executor takes the robot for not stopping
    # it: then it latches the e-stop and the plan fails (the default is services/actionlib.py's
    # CANCEL_GRACE, which imports zenoh, as this does not). Longer for a heavy robot that brakes
    # slowly, never so short that a stop under way is taken for none.
    cancel_grace: Annotated[float, Meta(ge=1.0, le=120.0)] = 10.0
