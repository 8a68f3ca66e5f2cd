"""Every key expression, defined once, each paired with its message type.

All keys live under `tether/<robot>/`. Topics are publications; services are queryables; an
action `X` uses the five keys zenoh-bridge-ros2dds uses for ROS 2 actions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from schemas.actions import (
    CancelGoal,
    CancelResponse,
    Feedback,
    GetResult,
    GoalProgress,
    GoalResponse,
    GoalStatus,
    ResultResponse,
    SendGoal,
)
from schemas.executor import ExecutePlanFeedback, ExecutePlanGoal, ExecutePlanResult
from schemas.incidents import ForgetIncident, ForgetReply, Incident, IncidentList, IncidentQuery, IncidentReport
from schemas.plan import GroundedPlan, ParseReply, Plan, PlanCheckReply, PlanText, ResolveReply
from schemas.planner import AskCancel, AskCancelReply, AskReply, AskRequest, PlannerAttempt, Recovery
from schemas.robot import (
    FollowJointTrajectoryFeedback,
    FollowJointTrajectoryGoal,
    FollowJointTrajectoryResult,
    GripperCommandFeedback,
    GripperCommandGoal,
    GripperCommandResult,
    JointState,
    NavigateToPoseFeedback,
    NavigateToPoseGoal,
    NavigateToPoseResult,
    Odometry,
    RobotDiagnostics,
    Twist,
)
from schemas.safety import (
    ApprovalDecision,
    ApprovalReply,
    ApprovalRequest,
    EStop,
    ModeReply,
    ModeRequest,
    PendingPlans,
    PlanApproval,
    ResetReply,
    ResetRequest,
    SafetyEvent,
    SafetyStatus,
)
from schemas.trace import RecorderStatus, TraceRecord
from schemas.world import (
    CameraImage,
    Empty,
    FaultReply,
    GroundTruth,
    InjectFault,
    MoveEntity,
    MoveReply,
    PerceivedHumans,
    PerceivedObjects,
    SceneDescription,
)

ROOT = "tether"
T = TypeVar("T")
Q = TypeVar("Q")
A = TypeVar("A")
G = TypeVar("G")
F = TypeVar("F")
R = TypeVar("R")


def prefix(robot: str) -> str:
    return f"{ROOT}/{robot}"


def bench_echo_key(robot: str, service: str) -> str:
    """The bare Zenoh echo a service declares for benchmarks (see services.runtime.BENCH_ECHO_ENV)."""
    return f"{prefix(robot)}/bench/raw_echo/{service}"


def bench_relay_key(robot: str) -> str:
    """Safety's bare relay to the sim's echo, for benchmarks: two hops with no checks."""
    return f"{prefix(robot)}/bench/raw_relay"


def bench_stream_in_key(robot: str) -> str:
    """Raw samples safety puts again, unchanged, on `bench_stream_out_key`: a topic's baseline."""
    return f"{prefix(robot)}/bench/raw_stream_in"


def bench_stream_out_key(robot: str) -> str:
    return f"{prefix(robot)}/bench/raw_stream_out"


def bench_load_key(robot: str) -> str:
    """Where bench.recorder puts its 1 KB messages: under the prefix, so the recorder takes them."""
    return f"{prefix(robot)}/bench/recorder_load"


def bench_count_key(robot: str) -> str:
    """bench.recorder's bare counting subscriber answers its count so far here (its baseline)."""
    return f"{prefix(robot)}/bench/recorder_count"


@dataclass(frozen=True)
class Topic(Generic[T]):
    path: str
    type: type[T]
    # Sent ahead of all other traffic and never dropped on a congested link (the stop, the heartbeat,
    # what safety lets the base do): a camera stream or a recording's flood must not hold them up.
    urgent: bool = False

    def key(self, robot: str) -> str:
        return f"{prefix(robot)}/{self.path}"


@dataclass(frozen=True)
class Service(Generic[Q, A]):
    path: str
    request: type[Q]
    reply: Any  # a Struct type or a tagged union of them
    # Request fields never published in traces (secrets).
    redact: tuple[str, ...] = ()

    def key(self, robot: str) -> str:
        return f"{prefix(robot)}/{self.path}"


@dataclass(frozen=True)
class ActionKeys(Generic[G, F, R]):
    path: str
    goal: type[G]
    feedback_type: type[F]
    result: type[R]
    send_goal: Service[Any, GoalResponse] = field(init=False)
    cancel_goal: Service[CancelGoal, CancelResponse] = field(init=False)
    get_result: Service[GetResult, Any] = field(init=False)
    # Not one of the five ROS 2 keys: where a goal is now, without waiting (for agents that poll).
    get_status: Service[GetResult, Any] = field(init=False)
    feedback: Topic[Any] = field(init=False)
    status: Topic[GoalStatus] = field(init=False)

    def __post_init__(self) -> None:
        base = f"{self.path}/_action"
        set_ = object.__setattr__
        set_(self, "send_goal", Service(f"{base}/send_goal", SendGoal[self.goal], GoalResponse))  # type: ignore[name-defined]
        set_(self, "cancel_goal", Service(f"{base}/cancel_goal", CancelGoal, CancelResponse))
        set_(self, "get_result", Service(f"{base}/get_result", GetResult, ResultResponse[self.result]))  # type: ignore[name-defined]
        progress = GoalProgress[self.feedback_type, self.result]  # type: ignore[name-defined]
        set_(self, "get_status", Service(f"{base}/get_status", GetResult, progress))
        set_(self, "feedback", Topic(f"{base}/feedback", Feedback[self.feedback_type]))  # type: ignore[name-defined]
        set_(self, "status", Topic(f"{base}/status", GoalStatus))

    def key(self, robot: str) -> str:
        return f"{prefix(robot)}/{self.path}"


# The planner side.
PLAN_PARSE: Service[PlanText, ParseReply] = Service("plan/parse", PlanText, ParseReply)
PLAN_RESOLVE: Service[Plan, ResolveReply] = Service("plan/resolve", Plan, ResolveReply)
EXECUTE_PLAN = ActionKeys("plan/execute", ExecutePlanGoal, ExecutePlanFeedback, ExecutePlanResult)
# Words to a checked plan: the planner asks an LLM, dry-runs each answer, feeds refusals back.
PLAN_ASK: Service[AskRequest, AskReply] = Service("plan/ask", AskRequest, AskReply)
# A caller stops the request it started (by the request id it chose): nothing more is sent for it.
PLAN_ASK_CANCEL: Service[AskCancel, AskCancelReply] = Service("plan/ask_cancel", AskCancel, AskCancelReply)
# Each model call and the dry run of its plan.
PLANNER_ATTEMPTS = Topic("planner/attempts", PlannerAttempt)
# Each recovery the planner asked the model for after a plan failed at execution, and its outcome.
PLANNER_RECOVERIES = Topic("planner/recoveries", Recovery)

# Commands to safety: the only doors towards the robot.
PLAN_CHECK: Service[GroundedPlan, PlanCheckReply] = Service("safety/check_plan", GroundedPlan, PlanCheckReply)
CMD_NAVIGATE = ActionKeys("cmd/navigate_to_pose", NavigateToPoseGoal, NavigateToPoseFeedback, NavigateToPoseResult)
CMD_TRAJECTORY = ActionKeys(
    "cmd/follow_joint_trajectory", FollowJointTrajectoryGoal, FollowJointTrajectoryFeedback, FollowJointTrajectoryResult
)
CMD_GRIPPER = ActionKeys("cmd/gripper_command", GripperCommandGoal, GripperCommandFeedback, GripperCommandResult)
# From programs (plans, agents): a value over a limit is refused, never silently clamped.
CMD_VEL = Topic("cmd/cmd_vel", Twist)
# From a person at a joystick or keyboard: clamped to the limits, and the clamping reported.
TELEOP_CMD_VEL = Topic("cmd/teleop/cmd_vel", Twist)

# Safety itself.
HEARTBEAT = Topic("safety/heartbeat", SafetyStatus, urgent=True)
ESTOP = Topic("safety/estop", EStop, urgent=True)
SAFETY_EVENTS = Topic("safety/events", SafetyEvent)
RESET: Service[ResetRequest, ResetReply] = Service("safety/reset", ResetRequest, ResetReply, redact=("token",))
# The control mode (operator only, with the token); the heartbeat says which is in force.
SET_MODE: Service[ModeRequest, ModeReply] = Service("safety/mode", ModeRequest, ModeReply, redact=("token",))
# Supervised mode: the executor asks before a plan's first motion; an operator decides; anyone with
# the read rights lists what waits.
APPROVAL_REQUEST: Service[ApprovalRequest, PlanApproval] = Service(
    "safety/approval/request", ApprovalRequest, PlanApproval
)
APPROVAL_DECIDE: Service[ApprovalDecision, ApprovalReply] = Service(
    "safety/approval/decide", ApprovalDecision, ApprovalReply, redact=("token",)
)
PENDING_PLANS: Service[Empty, PendingPlans] = Service("safety/approval/pending", Empty, PendingPlans)
# Safety's memory of incidents (written by safety alone): list them with the caution zones in force;
# an operator forgets one or clears a zone (with the token); the executor and the sim report what only
# they see; each new incident is published as safety records it.
INCIDENTS: Service[IncidentQuery, IncidentList] = Service("safety/incidents", IncidentQuery, IncidentList)
FORGET_INCIDENT: Service[ForgetIncident, ForgetReply] = Service(
    "safety/incidents/forget", ForgetIncident, ForgetReply, redact=("token",)
)
INCIDENT_REPORT = Topic("safety/incidents/report", IncidentReport)
NEW_INCIDENT = Topic("safety/incidents/new", Incident)

# The robot interface: only safety writes the command keys here.
ROBOT_NAVIGATE = ActionKeys("robot/navigate_to_pose", NavigateToPoseGoal, NavigateToPoseFeedback, NavigateToPoseResult)
ROBOT_TRAJECTORY = ActionKeys(
    "robot/follow_joint_trajectory",
    FollowJointTrajectoryGoal,
    FollowJointTrajectoryFeedback,
    FollowJointTrajectoryResult,
)
ROBOT_GRIPPER = ActionKeys("robot/gripper_command", GripperCommandGoal, GripperCommandFeedback, GripperCommandResult)
ROBOT_CMD_VEL = Topic("robot/cmd_vel", Twist, urgent=True)
JOINT_STATES = Topic("robot/joint_states", JointState)
ODOM = Topic("robot/odom", Odometry)

# What the robot perceives.
OBJECTS = Topic("world/objects", PerceivedObjects)
# A picture from the robot's camera, on request (for people and models to look at).
CAMERA_IMAGE: Service[Empty, CameraImage] = Service("robot/camera/image", Empty, CameraImage)
# What the backend finds wrong with the robot now (optional; `tether status` shows it).
ROBOT_DIAGNOSTICS: Service[Empty, RobotDiagnostics] = Service("robot/diagnostics", Empty, RobotDiagnostics)
HUMANS = Topic("world/humans", PerceivedHumans)
# The resolver's view of the world: objects where last seen, relations, a description for prompts.
SCENE: Service[Empty, SceneDescription] = Service("world/scene", Empty, SceneDescription)

# Simulator and recorder introspection.
GROUND_TRUTH: Service[Empty, GroundTruth] = Service("sim/ground_truth", Empty, GroundTruth)
# Moves an object or a person in the simulated world (the world changing, not the robot acting).
SIM_MOVE: Service[MoveEntity, MoveReply] = Service("sim/move", MoveEntity, MoveReply)
# Injects a fault in the simulated world (an object slipping, a doorway blocked, an object hidden).
SIM_FAULT: Service[InjectFault, FaultReply] = Service("sim/fault", InjectFault, FaultReply)
RECORDER_STATUS: Service[Empty, RecorderStatus] = Service("recorder/status", Empty, RecorderStatus)

ACTIONS: tuple[ActionKeys[Any, Any, Any], ...] = (
    EXECUTE_PLAN,
    CMD_NAVIGATE,
    CMD_TRAJECTORY,
    CMD_GRIPPER,
    ROBOT_NAVIGATE,
    ROBOT_TRAJECTORY,
    ROBOT_GRIPPER,
)
TOPICS: tuple[Topic[Any], ...] = (
    CMD_VEL,
    TELEOP_CMD_VEL,
    HEARTBEAT,
    ESTOP,
    SAFETY_EVENTS,
    ROBOT_CMD_VEL,
    JOINT_STATES,
    ODOM,
    OBJECTS,
    HUMANS,
    PLANNER_ATTEMPTS,
    PLANNER_RECOVERIES,
    INCIDENT_REPORT,
    NEW_INCIDENT,
    *(a.feedback for a in ACTIONS),
    *(a.status for a in ACTIONS),
)
SERVICES: tuple[Service[Any, Any], ...] = (
    PLAN_PARSE,
    PLAN_RESOLVE,
    PLAN_CHECK,
    RESET,
    SET_MODE,
    APPROVAL_REQUEST,
    APPROVAL_DECIDE,
    PENDING_PLANS,
    INCIDENTS,
    FORGET_INCIDENT,
    SCENE,
    GROUND_TRUTH,
    SIM_MOVE,
    SIM_FAULT,
    RECORDER_STATUS,
    CAMERA_IMAGE,
    ROBOT_DIAGNOSTICS,
    *(s for a in ACTIONS for s in (a.send_goal, a.cancel_goal, a.get_result, a.get_status)),
)


def alive_key(robot: str, service: str = "*") -> str:
    return f"{prefix(robot)}/alive/{service}"


def process_key(robot: str, service: str = "*") -> str:
    """Where each service answers with a schemas.process.ProcessStatus: its host, pid and memory."""
    return f"{prefix(robot)}/_process/{service}"


def trace_key(robot: str, service: str, path: str) -> str:
    return f"{prefix(robot)}/_trace/{service}/{path}"


def all_keys(robot: str) -> str:
    return f"{prefix(robot)}/**"


def topic_for_key(robot: str, key: str) -> Topic[Any] | None:
    """The topic a published key belongs to, for the recorder's schemas; None if not ours."""
    root = prefix(robot) + "/"
    if not key.startswith(root):
        return None
    path = key[len(root) :]
    if path.startswith("_trace/"):
        return Topic(path, TraceRecord)
    for topic in TOPICS:
        if topic.path == path:
            return topic
    return None
