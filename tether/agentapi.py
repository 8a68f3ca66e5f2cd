"""What an agent may ask of the robot, over Zenoh, each answer as text a model can act on.

Every motion is a plan sent to the executor, so it is parsed, resolved and checked by safety like
any other; an agent can stop the robot (cancel, e-stop) but never reset the e-stop, lift a limit or
change the policy: nothing here names those keys.
"""

from __future__ import annotations

import base64
import binascii
import io
import json
import logging
import threading
import time
import uuid
from dataclasses import dataclass
from typing import Any

from schemas import keys
from schemas.actions import CancelGoal, GetResult
from schemas.common import Pose2D
from schemas.executor import ExecutePlanGoal
from schemas.incidents import IncidentList
from schemas.plan import MAX_PLAN_BYTES
from schemas.planner import AskCancel, AskCancelReply, AskReply, AskRequest
from schemas.safety import EstopSource
from schemas.world import CameraImage, Empty
from services.agent import feedback
from services.errors import CallError, GoalRejected
from services.planner.prompt import hazards_block, hazards_query
from services.runtime import Node
from tether.client import PlanSender, next_message, trigger_estop

log = logging.getLogger(__name__)

# How long an action tool waits for its plan to be parsed, resolved and approved before it returns
# the goal id (the plan goes on after that; a model polls get_goal_status).
START_WAIT = 10.0
CALL_TIMEOUT = 5.0
# describe_scene asks safety for the known hazards near the robot this long at most (the scene comes anyway).
HAZARDS_TIMEOUT = 1.0
# plan_and_execute asks the model up to a few times, each answer dry-run through the pipeline; it
# answers within this (below the 60 s MCP clients commonly wait), or gives up having sent nothing.
ASK_TIMEOUT = 50.0
# How long the cancel of a request whose caller went waits for the planner: a send under way holds it
# up to its timeout (the executor preempting a plan), then the cancel of the goal sent.
CANCEL_ASK_TIMEOUT = 20.0
# The most base64 a camera picture may be: Anthropic's API refuses an image over 5 MB.
MAX_PICTURE_CHARS = 5 * 1024 * 1024


class AgentError(Exception):
    """A call that could not be made (a service down, a bad argument): the text says which and why."""


@dataclass(frozen=True)
class Picture:
    data: str  # base64
    mime_type: str
    caption: str


class Call:
    """One tool call, as seen from the thread carrying it out: whether its caller has gone (it canceled
    the call, or disconnected), the goal the call sent and the planner request it is making. A goal
    whose id was only in the answer nobody got is canceled: no one else could follow it or stop it; a
    request still with the planner is canceled there, before it sends a plan. `sent`, `asking` and
    `abandon` decide under one lock, so each is canceled once, by whichever side comes second."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._abandoned = False
        self._goal_id: str | None = None
        self._request_id: str | None = None

    @property
    def abandoned(self) -> bool:
        with self._lock:
            return self._abandoned

    def sent(self, goal_id: str) -> bool:
        """Note the goal this call sent; True when its caller has already gone (the goal is to be canceled)."""
        with self._lock:
            self._goal_id = goal_id
            return self._abandoned

    def asking(self, request_id: str) -> bool:
        """Note the planner request this call is about to make; True when its caller has already gone
        (it is not to be made)."""
        with self._lock:
            self._request_id = request_id
            return self._abandoned

    def asked(self) -> None:
        """The planner answered (or the ask failed): the request is over, a goal it names goes by `sent`."""
        with self._lock:
            self._request_id = None

    def answered(self) -> None:
        """The answer, goal id and all, is on its way to the caller: nothing is canceled after this."""
        with self._lock:
            self._goal_id = None

    def abandon(self) -> tuple[str | None, str | None]:
        """Mark the caller gone; for the caller of this to cancel: the goal this call sent and the
        planner request it is making, each None when there is none."""
        with self._lock:
            self._abandoned = True
            goal_id, self._goal_id = self._goal_id, None
            request_id, self._request_id = self._request_id, None
            return goal_id, request_id


class AgentAPI:
    def __init__(self, node: Node) -> None:
        self.node = node
        self.sender = PlanSender(node)

    # Actions: each one a plan for the executor

    def action(self, name: str, arguments: dict[str, Any], call: Call | None = None) -> str:
        """One action as a one-step plan (the parser checks names, types, units and bounds)."""
        step = {**arguments, "action": name}  # the tool's name decides the action, never an argument
        return self.execute_plan({"plan": [step]}, call)

    def execute_plan(self, plan: Any, call: Call | None = None) -> str:
        # As written: escaped, an "é" took six bytes and a plan within the tool's bounds went over the
        # executor's limit.
        text = plan if isinstance(plan, str) else json.dumps(plan, ensure_ascii=False)
        if (size := len(text.encode())) > MAX_PLAN_BYTES:
            # The executor drops a goal this long undecoded, which read as "not reachable".
            return f"rejected: the plan is {size} bytes as JSON; the limit is {MAX_PLAN_BYTES}: shorten its texts"
        goal = ExecutePlanGoal(text=text, format="auto")
        call = call or Call()
        if call.abandoned:
            return "not sent: the call was canceled"
        try:
            handle = self.sender.send(goal)
        except GoalRejected as exc:
            return feedback.rejected_text(exc.reason)
        except CallError as exc:
            raise AgentError(f"the executor is not reachable: {exc}") from None
        if call.sent(handle.goal_id):
            self.sender.forget(handle.goal_id)
            return self.cancel_unheard(handle.goal_id)
        try:
            run = self.sender.wait(handle, START_WAIT, until_started=True)
        except CallError:  # not ended, and not started within START_WAIT: still being checked
            return feedback.started_text(handle.goal_id, None, None, checked=False)
        finally:
            self.sender.forget(handle.goal_id)  # the agent follows it with get_goal_status from here
        return feedback.started_text(handle.goal_id, run.result, run.latest, checked=run.executing)

    def plan_and_execute(self, request: str, dry_run: bool, call: Call | None = None) -> str:
        call = call or Call()
        # Named here, so that a caller who goes stops the request in the planner (cancel_unheard_ask).
        request_id = uuid.uuid4().hex
        if call.asking(request_id):
            return "not asked: the call was canceled"
        try:
            # The planner never sends a plan after the deadline: a call that timed out here moves nothing.
            deadline = time.time() + ASK_TIMEOUT
            asked = AskRequest(text=request, dry_run=dry_run, deadline=deadline, request_id=request_id)
            reply: AskReply = self.node.call(keys.PLAN_ASK, asked, timeout=ASK_TIMEOUT + 5.0)
        except CallError as exc:
            raise AgentError(f"the planner did not answer: {exc.error.message}") from None
        finally:
            call.asked()
        # A plan sent before a cancel reached the planner, or by one that cannot cancel (an older one).
        if reply.goal_id and call.sent(reply.goal_id):
            return self.cancel_unheard(reply.goal_id)
        return feedback.ask_text(reply)

    # Following and stopping

    def goal_status(self, goal_id: str) -> str:
        goal_id = _goal_id(goal_id)
        try:
            progress = self.node.call(keys.EXECUTE_PLAN.get_status, GetResult(goal_id=goal_id), timeout=CALL_TIMEOUT)
        except CallError as exc:
            return f"unknown goal {goal_id}: {exc.error.message}"
        return feedback.progress_text(progress)

    def cancel(self, goal_id: str) -> str:
        goal_id = _goal_id(goal_id)
        try:
            reply = self.node.call(keys.EXECUTE_PLAN.cancel_goal, CancelGoal(goal_id=goal_id), timeout=CALL_TIMEOUT)
        except CallError as exc:
            raise AgentError(f"cancel of {goal_id} failed: {exc.error.message}") from None
        if not reply.accepted:
            return f"not canceled: {reply.reason or 'no such running goal'}"
        return f"canceling {goal_id}: the robot stops; get_goal_status shows when it has ended"

    def cancel_unheard(self, goal_id: str) -> str:
        """Cancel a goal whose caller went before it heard the goal's id (Call)."""
        log.warning("canceling goal %s: the agent that sent it went before it was told its id", goal_id)
        try:
            return self.cancel(goal_id)
        except AgentError as exc:
            log.error("goal %s goes on: %s", goal_id, exc)
            return str(exc)

    def cancel_unheard_ask(self, request_id: str) -> None:
        """Cancel a planner request whose caller went before its answer (Call): the planner sends no
        plan for it after this, and cancels the one it sent already. A planner that does not serve
        plan/ask_cancel (an older one) sends its plan anyway: that goal is canceled once its answer
        names it."""
        log.warning("canceling planner request %s: the agent that made it went before the answer", request_id)
        try:
            found: AskCancelReply = self.node.call(
                keys.PLAN_ASK_CANCEL, AskCancel(request_id=request_id), timeout=CANCEL_ASK_TIMEOUT
            )
        except CallError as exc:
            log.warning(
                "the planner did not cancel request %s (%s): a plan it sends is canceled as its answer comes",
                request_id,
                exc.error.message,
            )
            return
        log.info("planner request %s: %s", request_id, found.reason)

    def emergency_stop(self, reason: str) -> str:
        status = trigger_estop(self.node, EstopSource.AGENT, reason)
        if status is None:
            return (
                "e-stop not confirmed: sent, but safety did not confirm it within 2 s; assume the robot may still move"
            )
        return "e-stop latched: nothing moves until a human operator resets it"

    # Reading

    def robot_state(self) -> str:
        beat = next_message(self.node, keys.HEARTBEAT, 1.0)
        odom = next_message(self.node, keys.ODOM, 1.0)
        state: dict[str, Any] = {
            "estop": (
                {"latched": beat.estop.latched, "reason": beat.estop.reason}
                if beat is not None
                else "unknown: no heartbeat from safety (the robot will not move)"
            ),
            "speed_scale": beat.speed_scale if beat is not None else None,
            "speed_note": beat.speed_reason if beat is not None else "",
            "pose": (
                {"x": round(odom.pose.x, 3), "y": round(odom.pose.y, 3), "yaw_rad": round(odom.pose.yaw, 3)}
                if odom is not None
                else None
            ),
            "moving": odom is not None and (abs(odom.linear_x) > 0.01 or abs(odom.angular_z) > 0.01),
        }
        return feedback.data_json("robot state", state)

    def scene(self) -> str:
        """The world model's scene, then the known hazards near the robot (safety's memory of incidents),
        each marked as data; a safety that does not answer is one line, the scene still comes."""
        scene = self._scene()
        return feedback.as_data("world model", scene.text) + "\n\n" + hazards_block(self._hazards(scene.robot))

    def _hazards(self, robot: Pose2D | None) -> IncidentList | None:
        """Incidents and caution zones near the robot, as the planner asks for them (prompt.hazards_query);
        None when safety did not answer."""
        try:
            found: IncidentList = self.node.call(keys.INCIDENTS, hazards_query(robot), timeout=HAZARDS_TIMEOUT)
        except CallError:
            return None
        return found

    def objects(self) -> str:
        scene = self._scene()
        listed = [
            {
                "name": o.name,
                "id": o.id,
                "room": o.room,
                "on": o.on,
                "position_m": [round(o.position.x, 2), round(o.position.y, 2), round(o.position.z, 2)],
            }
            for o in scene.objects
        ]
        return feedback.data_json("world model", listed)

    def picture(self) -> Picture:
        try:
            image: CameraImage = self.node.call(keys.CAMERA_IMAGE, Empty(), timeout=CALL_TIMEOUT)
        except CallError as exc:
            # The backend's reason quotes the robot (its image's encoding and format, as it named them).
            raise AgentError("no camera image:\n" + feedback.as_data("camera", exc.error.message)) from None
        if (problem := picture_problem(image)) is not None:
            raise AgentError(f"no camera image: the robot's picture {problem}")
        caption = f"the robot's camera, {image.width} x {image.height} pixels"
        return Picture(image.data, image.mime_type, caption)

    def _scene(self) -> Any:
        try:
            return self.node.call(keys.SCENE, Empty(), timeout=CALL_TIMEOUT)
        except CallError as exc:
            raise AgentError(f"the world model is not reachable: {exc.error.message}") from None


def picture_problem(image: CameraImage) -> str | None:
    """Why the robot's picture cannot go to a model, or None. A model's API refuses an image that is
    not what its mime type says, or is over 5 MB, and the image stays in the agent's conversation,
    sent again with every later request. So it must be base64 of a PNG that decodes whole, of the
    size it claims, within MAX_PICTURE_CHARS."""
    if len(image.data) > MAX_PICTURE_CHARS:
        return f"is {len(image.data)} characters of base64; a model takes at most {MAX_PICTURE_CHARS}"
    try:
        png = base64.b64decode(image.data, validate=True)
    except binascii.Error as exc:
        return f"is not base64 ({exc})"
    from PIL import Image, UnidentifiedImageError  # only when asked for a picture

    try:
        with Image.open(io.BytesIO(png), formats=["PNG"]) as picture:
            # From the header, before decoding: a small file cannot make it decode far more pixels.
            if picture.size != (image.width, image.height):
                width, height = picture.size
                return f"is {width} x {height} pixels, not the {image.width} x {image.height} it claims"
            picture.load()
    except UnidentifiedImageError:
        return f"is not a PNG (it begins {png[:8]!r})"
    except Exception as exc:  # what Pillow raises for a file it cannot read is not one class
        return f"is not a PNG that decodes: {exc}"
    return None


def _goal_id(text: str) -> str:
    """A goal id as a model passes it back: stray spaces and a closing full stop dropped."""
    return text.strip().rstrip(".")
