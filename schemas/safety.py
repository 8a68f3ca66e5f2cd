"""Safety: heartbeat with the e-stop latch and the control mode, e-stop triggers, operator reset,
mode changes and plan approvals, decision events."""

from __future__ import annotations

import enum
from typing import Annotated

import msgspec
from msgspec import Meta

from schemas.actions import GoalId
from schemas.common import Frozen, Name, Text
from schemas.plan import GroundedPlan


class EstopSource(enum.StrEnum):
    """Who may trigger the e-stop. Anyone may; only an operator's token resets it."""

    OPERATOR = "operator"  # a person: `tether estop`, a hardware button bridged to the key
    EXECUTOR = "executor"  # the plan runner, when it finds the robot in a state it cannot handle
    AGENT = "agent"  # an LLM agent or MCP tool
    WATCHDOG = "watchdog"  # safety's watchdog: the robot's state stopped arriving while it moved
    MONITOR = "monitor"  # safety's monitors: measured motion beyond a limit, the base in a keep-out zone


class ControlMode(enum.StrEnum):
    """Who drives. Only the operator's identity changes it (`tether mode`); safety holds it."""

    DIRECT = "direct"  # only a person drives (teleop); plans are refused
    SHARED = "shared"  # a person drives (teleop); plans are refused
    SUPERVISED = "supervised"  # a plan moves the robot only once an operator approved it
    AUTONOMOUS = "autonomous"  # a plan safety approves runs (the default)


class EstopState(Frozen):
    latched: bool
    source: Text = ""
    reason: Text = ""
    stamp: float = 0.0


class SafetyStatus(Frozen):
    """The heartbeat. The robot stops when it stops arriving.

    `speed_scale` is speed-and-separation monitoring: the fraction of the policy's speed the robot
    may use now (0 pauses motion without ending goals), with `speed_reason` saying why. The arm
    applies it to its trajectories; the base keeps within `max_linear_speed` and `max_angular_speed`
    (the policy's limits times the scale; None: the robot's own times the scale). `policy_hash`
    names the policy in force.
    """

    seq: Annotated[int, Meta(ge=0)]
    stamp: float
    estop: EstopState
    speed_scale: Annotated[float, Meta(ge=0.0, le=1.0)] = 1.0
    speed_reason: Text = ""
    max_linear_speed: Annotated[float, Meta(ge=0.0, le=10.0)] | None = None
    max_angular_speed: Annotated[float, Meta(ge=0.0, le=20.0)] | None = None
    policy_hash: Annotated[str, Meta(max_length=80)] = ""
    mode: ControlMode = ControlMode.AUTONOMOUS


class EStop(Frozen):
    """Anyone may publish this; it latches until an operator resets it."""

    source: EstopSource
    reason: Text = ""


class ResetRequest(Frozen):
    operator: Name
    token: Annotated[str, Meta(max_length=256)]


class ResetReply(Frozen):
    ok: bool
    message: Text


OperatorToken = Annotated[str, Meta(max_length=256)]


class ModeState(Frozen):
    """The control mode as safety writes it down (it survives a restart)."""

    mode: ControlMode
    source: Text = ""
    stamp: float = 0.0


class ModeRequest(Frozen):
    """Set the control mode: only with the operator's token (as a reset)."""

    operator: Name
    token: OperatorToken
    mode: ControlMode


class ModeReply(Frozen):
    """`mode`: the mode now (the old one when refused)."""

    ok: bool
    message: Text
    mode: ControlMode


class ApprovalState(enum.StrEnum):
    NOT_NEEDED = "not_needed"  # the mode is autonomous: safety's plan check is enough
    PENDING = "pending"  # supervised: waits for an operator
    APPROVED = "approved"  # an operator approved it; it may move the robot until it ends
    PAUSED = "paused"  # an operator paused it while it ran: a program's motion is refused until resumed
    DENIED = "denied"  # an operator denied it, or the mode or safety's check refuses it: it never moves
    FINISHED = "finished"  # it ended (ran, was canceled) and is remembered for a while


MAX_PLAN_LINES = 64


class PlanApproval(Frozen):
    """Where a plan stands with safety's approval. `steps`: the plan's steps and route as safety read
    them; `checks`: safety's dry run of the whole plan (what it checked); `requested`, `decided`: wall
    clock seconds; `by`: the operator who decided; `pauses`: how often an operator paused it (the
    executor tells a failure a pause caused from one of its own by it)."""

    goal_id: GoalId
    state: ApprovalState
    reason: Text = ""
    steps: Annotated[list[Text], Meta(max_length=MAX_PLAN_LINES)] = []
    checks: Annotated[list[Text], Meta(max_length=MAX_PLAN_LINES)] = []
    requested: float = 0.0
    decided: float = 0.0
    by: Annotated[str, Meta(max_length=200)] = ""
    pauses: Annotated[int, Meta(ge=0)] = 0


class ApprovalRequest(Frozen):
    """From the executor before a plan's first motion: may `plan` (goal `goal_id`) move the robot?
    Asking again is answered from what safety holds; `wait`: seconds to wait for a decision while it
    is pending."""

    goal_id: GoalId
    plan: GroundedPlan
    wait: Annotated[float, Meta(ge=0.0, le=5.0)] = 0.0


class ApprovalAction(enum.StrEnum):
    APPROVE = "approve"  # a pending plan may move the robot
    DENY = "deny"  # a pending or paused plan ends; it moves no more
    PAUSE = "pause"  # an approved, running plan stops; teleop drives meanwhile
    RESUME = "resume"  # a paused plan moves again (checked once more from where the robot is)


class ApprovalDecision(Frozen):
    """An operator decides on a plan of supervised mode, with the operator's token: `action`, or
    (older callers, and recordings made before pause) `approve`: true approve, false deny. Exactly
    one of the two is given."""

    operator: Name
    token: OperatorToken
    goal_id: GoalId
    approve: bool | None = None
    reason: Text = ""
    action: ApprovalAction | None = None


class ApprovalReply(Frozen):
    ok: bool
    message: Text
    approval: PlanApproval | None = None


class PendingPlans(Frozen):
    """The plans waiting for an operator, the oldest first; `paused`: those an operator paused."""

    mode: ControlMode
    plans: list[PlanApproval] = []
    paused: list[PlanApproval] = []


class Decision(enum.StrEnum):
    APPROVED = "approved"
    VETOED = "vetoed"
    CLAMPED = "clamped"
    STOPPED = "stopped"
    LATCHED = "latched"
    RESET = "reset"
    # The speed limit near people changed (slowed, paused or back to full speed).
    LIMITED = "limited"
    # The control mode changed (an operator's `tether mode`).
    MODE = "mode"
    # A plan waits for an operator (supervised mode); an operator denied one.
    AWAITING_APPROVAL = "awaiting_approval"
    DENIED = "denied"
    # An operator paused a running plan (teleop may take over), or resumed it.
    PAUSED = "paused"
    RESUMED = "resumed"
    # An operator forgot an incident, or cleared the caution zone it counted towards (safety's memory).
    FORGOTTEN = "forgotten"
    CLEARED = "cleared"


class Rule(enum.StrEnum):
    """The rules safety applies, named in every event (services/safety/policy.toml sets their limits)."""

    ESTOP = "estop"  # nothing moves while the e-stop is latched
    OPERATOR = "operator"  # only the operator's token resets the e-stop, sets the mode, approves plans
    MODE = "mode"  # what the control mode lets move (direct, shared: no plans; supervised: approved ones)
    APPROVAL = "approval"  # in supervised mode a plan moves only once an operator approved it
    POSE_KNOWN = "pose_known"  # motion needs recent odometry / joint states
    MAP = "map"  # the base stays on the map
    KEEP_OUT = "keep_out"  # the base's footprint stays out of keep-out zones
    OBSTACLE = "obstacle"  # the base's footprint, driving its route, touches no wall or furniture
    BASE_SPEED = "base_speed"
    BASE_ACCELERATION = "base_acceleration"
    CMD_VEL_HORIZON = "cmd_vel_horizon"  # a held cmd_vel must not reach a zone or leave the map
    JOINT_LIMITS = "joint_limits"
    JOINT_SPEED = "joint_speed"
    WORKSPACE = "workspace"  # the end effector inside its box
    ARM_KEEP_OUT = "arm_keep_out"  # the end effector out of keep-out zones
    BASE_STILL = "base_still"  # the arm moves only while the base stands still
    ONE_MOTION = "one_motion"  # the arm and the base never move at once: not while the other's goal runs
    PAYLOAD = "payload"
    GRIPPER_FORCE = "gripper_force"
    GRIPPER_DROP = "gripper_drop"  # no opening the gripper over the floor with something in it
    HUMAN_SEPARATION = "human_separation"
    COMMAND_RATE = "command_rate"
    PLAN = "plan"  # a plan's structure (labels, on_failure ranges)
    MONITOR_SPEED = "monitor_speed"  # measured base speed within the allowed speed
    MONITOR_JOINT_SPEED = "monitor_joint_speed"
    MONITOR_KEEP_OUT = "monitor_keep_out"  # the measured pose out of keep-out zones
    WATCHDOG = "watchdog"  # the robot's state keeps arriving while it moves
    CAUTION_ZONE = "caution_zone"  # slower where incidents repeated (safety's memory), until an operator clears it


# In a `latched` event's values (1.0): the e-stop was asked for while already latched; the latch
# stays as the first one set it (the event's reason names both).
ALREADY_LATCHED = "already_latched"


class SafetyEvent(Frozen):
    """One safety decision: what was asked, what was decided, by which rule, on which measurements.

    `rule` is the rule that decided a veto, clamp or latch (None for an approval); `checks` the rules that
    were applied; `values` the measured values and limits the decision rests on (SI units, named
    like `speed_mps` and `limit_mps`, or ALREADY_LATCHED); `policy_hash` the sha256 of the policy file in force.
    """

    stamp: float
    key: Text
    decision: Decision
    reason: Text = ""
    rule: Rule | None = None
    checks: Annotated[list[Rule], Meta(max_length=64)] = []
    values: Annotated[dict[Annotated[str, Meta(max_length=64)], float], Meta(max_length=64)] = {}
    policy_hash: Annotated[str, Meta(max_length=80)] = ""
    command: msgspec.Raw = msgspec.field(default_factory=lambda: msgspec.Raw(b"null"))
