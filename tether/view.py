"""`tether view`: the robot live in Foxglove, served over the Foxglove WebSocket protocol with foxglove-sdk.

What Zenoh delivers is only stored here (the latest message of each kind, and a bounded queue of log
lines), never converted or sent on Zenoh's threads: one publishing thread turns it into Foxglove's
messages and hands them to the SDK, whose server keeps a bounded backlog per client and drops the
oldest for a client that does not keep up. A slow or hostile viewer costs this process at most a
few buffers; safety and the other services never wait for it (they do not know it is there).

Teleop the other way (only with --teleop): on loopback the server takes client publish (Foxglove's
Teleop panel) on one topic, tether/viewteleop.py decides what is taken and when to stop, and
TeleopBridge puts each twist on cmd/teleop/cmd_vel, where safety clamps it as it clamps `tether teleop`.
"""

from __future__ import annotations

import collections
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import foxglove
import msgspec
import typer
from foxglove.websocket import Capability, ChannelView, Client, ClientChannel, StatusLevel

from schemas import keys
from schemas.actions import Feedback, GoalStatus, SendGoal
from schemas.common import DECODE_ERRORS
from schemas.executor import ExecutePlanFeedback
from schemas.robot import JointState, NavigateToPoseGoal, Odometry, Twist
from schemas.safety import SafetyEvent, SafetyStatus
from schemas.trace import TraceRecord
from schemas.world import Empty, PerceivedHumans, PerceivedObjects
from services import runtime
from services.bundled import DEFAULT_POLICY, world_path
from services.errors import CallError
from services.recorder import scene3d
from services.recorder.mcapfile import json_schema
from services.repeats import RepeatLog
from services.runtime import ConfigError, Node, NodeSettings
from services.safety.config import SafetyConfig
from tether.client import signature_shaped
from tether.runservice import leave
from tether.teleop import finite
from tether.viewteleop import TELEOP_TOPIC, Refused, TeleopGate

log = logging.getLogger(__name__)

LOOPBACK = ("127.0.0.1", "localhost", "::1")
DEFAULT_PORT = 8765
PUBLISH_PERIOD = 0.05  # s: 20 Hz is as fast as the 3D panel is worth updating
STATIC_PERIOD = 5.0  # s: the static scene again, for a viewer whose first copy was dropped
# s between two copies of the static scene for viewers that subscribed: the SDK sends it to every
# subscriber, so a client subscribing in a loop must not have it broadcast on each pass.
SCENE_AGAIN = 0.5
LOG_BACKLOG = 256  # log lines waiting for the publishing thread; the oldest go first
CLIENT_BACKLOG = 64  # messages the SDK holds per viewer before dropping its oldest
CAMERA_TIMEOUT = 2.0  # s for one camera picture
TELEOP_TICK = 0.02  # s between two looks of the deadman: a stop goes out at most this late
# s between two status messages to Foxglove users; what came in between goes out in one. A status
# goes to every viewer's control queue, which the SDK holds to CLIENT_BACKLOG and disconnects a
# viewer when full: one client's refusals in a loop must not cost the others their connection.
NOTICE_PERIOD = 0.5
HELPER_JOIN = CAMERA_TIMEOUT + 1.0  # s to wait for the teleop and camera threads to end at exit
# s to wait for Foxglove's server to stop: its stop waits for every viewer to take what was sent to it,
# and one that stopped reading (a laptop asleep, a hostile client) never does: Ctrl-C never ended the view.
SERVER_STOP_WAIT = 3.0
EXIT_USAGE, EXIT_UNREACHABLE, EXIT_SERVE = 2, 3, 1


class Latest:
    """The newest payload of each kind, newest wins: O(1) for Zenoh's threads, taken whole by the publisher."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._slots: dict[str, tuple[str, bytes]] = {}
        self.replaced = 0  # payloads overwritten before they were published

    def put(self, kind: str, key: str, payload: bytes) -> None:
        with self._lock:
            if kind in self._slots:
                self.replaced += 1
            self._slots[kind] = (key, payload)

    def take(self) -> dict[str, tuple[str, bytes]]:
        with self._lock:
            slots, self._slots = self._slots, {}
        return slots


class LogQueue:
    """Log lines in order, at most `size`: when full, the oldest is dropped and counted."""

    def __init__(self, size: int = LOG_BACKLOG) -> None:
        self._lock = threading.Lock()
        self._items: collections.deque[tuple[str, str, bytes]] = collections.deque(maxlen=size)
        self.dropped = 0

    def put(self, kind: str, key: str, payload: bytes) -> None:
        with self._lock:
            if len(self._items) == self._items.maxlen:
                self.dropped += 1
            self._items.append((kind, key, payload))

    def take(self) -> list[tuple[str, str, bytes]]:
        with self._lock:
            items = list(self._items)
            self._items.clear()
        return items


@dataclass(frozen=True)
class Inputs:
    """Where each kind comes from: the Zenoh key expression, and whether every message counts (log) or the latest."""

    kind: str
    key_expr: str
    every: bool = False


def inputs(robot: str) -> list[Inputs]:
    plan = keys.EXECUTE_PLAN
    return [
        Inputs("odom", keys.ODOM.key(robot)),
        Inputs("joints", keys.JOINT_STATES.key(robot)),
        Inputs("objects", keys.OBJECTS.key(robot)),
        Inputs("humans", keys.HUMANS.key(robot)),
        Inputs("heartbeat", keys.HEARTBEAT.key(robot)),
        # The route the robot was given: the navigation goal as the backend received it (its trace).
        Inputs("route", keys.trace_key(robot, "*", keys.ROBOT_NAVIGATE.send_goal.path)),
        Inputs("safety", keys.SAFETY_EVENTS.key(robot), every=True),
        Inputs("feedback", plan.feedback.key(robot), every=True),
        Inputs("plan", plan.status.key(robot), every=True),
    ]


# tether's own messages passed through as they are (JSON, their schemas as in recordings), for plots
# and raw views: the same topics a recording has.
PASSTHROUGH: dict[str, keys.Topic[Any]] = {
    "odom": keys.ODOM,
    "heartbeat": keys.HEARTBEAT,
    "plan": keys.EXECUTE_PLAN.status,
}


class ArmFrames:
    """The arm's links as frames under the base, from joint states and the arm's URDF (pinocchio).

    Each link is given relative to panda_link0, which stands on the base at the world file's arm mount."""

    ROOT = "panda_link0"

    def __init__(self, arm_urdf: str, mount: tuple[float, float, float]) -> None:
        import pinocchio as pin  # a second or so to load: only when the view starts

        from services.robotmodel import arm_urdf_path

        self._pin = pin
        self.model = pin.buildModelFromUrdf(str(arm_urdf_path(arm_urdf)))
        self.data = self.model.createData()
        self.mount = mount
        self.links = [
            (i, f.name) for i, f in enumerate(self.model.frames) if f.type == pin.FrameType.BODY and f.name != self.ROOT
        ]

    def transforms(self, joints: JointState) -> list[scene3d.FrameTransform]:
        pin = self._pin
        q = pin.neutral(self.model)
        for name, position in zip(joints.name, joints.position, strict=False):
            if self.model.existJointName(name):
                joint = self.model.joints[self.model.getJointId(name)]
                if joint.nq == 1 and math.isfinite(position):
                    q[joint.idx_q] = position
        pin.framesForwardKinematics(self.model, self.data, q)
        t = scene3d.stamp(joints.stamp)
        mx, my, mz = self.mount
        frames = [
            scene3d.FrameTransform(
                timestamp=t,
                parent_frame_id=scene3d.BASE_FRAME,
                child_frame_id=self.ROOT,
                translation=scene3d.Vector3(x=mx, y=my, z=mz),
                rotation=scene3d.Quaternion(),
            )
        ]
        for index, name in self.links:
            placement = self.data.oMf[index]
            quat = pin.Quaternion(placement.rotation)
            p = placement.translation
            frames.append(
                scene3d.FrameTransform(
                    timestamp=t,
                    parent_frame_id=self.ROOT,
                    child_frame_id=name,
                    translation=scene3d.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                    rotation=scene3d.Quaternion(x=float(quat.x), y=float(quat.y), z=float(quat.z), w=float(quat.w)),
                )
            )
        return frames


class Throttle(logging.Filter):
    """At most `burst` lines of the SDK's log per `window` seconds: it logs every bad frame a viewer sends,
    and a viewer sending garbage as fast as it can must not fill the disk."""

    def __init__(self, burst: int = 20, window: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.burst, self.window, self._clock = burst, window, clock
        self._opened = -math.inf
        self._count = 0
        self.suppressed = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.name.startswith("foxglove"):
            return True
        now = self._clock()
        if now - self._opened >= self.window:
            if self.suppressed:
                record.msg = f"{record.msg} ({self.suppressed} more lines of the Foxglove server were not logged)"
            self._opened, self._count, self.suppressed = now, 0, 0
        self._count += 1
        if self._count > self.burst:
            self.suppressed += 1
            return False
        return True


def json_channel(context: foxglove.Context, topic: str, name: str, schema: bytes) -> foxglove.Channel:
    return foxglove.Channel(
        topic,
        schema=foxglove.Schema(name=name, encoding="jsonschema", data=schema),
        message_encoding="json",
        context=context,
    )


class LiveView:
    """Zenoh in (stored only), Foxglove channels out (from one publishing thread, `publish_once`)."""

    def __init__(
        self,
        robot: str,
        scene: scene3d.Scene,
        context: foxglove.Context,
        arm: ArmFrames | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.robot = robot
        self.scene = scene
        self.arm = arm
        self._clock = clock
        self.latest = Latest()
        self.logs = LogQueue()
        self.undecodable = RepeatLog("undecodable messages dropped")
        self.unshowable = RepeatLog("messages not shown")
        self._static_due = threading.Event()
        self._static_due.set()
        self._static_sent = 0.0
        self._base: scene3d.FrameTransform | None = None
        self._arm_frames: list[scene3d.FrameTransform] = []
        self.channels: dict[str, foxglove.Channel] = {
            topic: json_channel(context, topic, scene3d.SCHEMA_NAMES[type_], scene3d.schema_document(type_))
            for topic, type_ in scene3d.TOPIC_TYPES.items()
        }
        for topic in PASSTHROUGH.values():
            name, schema = json_schema(topic.type)
            self.channels[topic.key(robot)] = json_channel(context, topic.key(robot), name, schema)
        self._decoders: dict[str, msgspec.json.Decoder[Any]] = {
            "odom": runtime.decoder(Odometry),
            "joints": runtime.decoder(JointState),
            "objects": runtime.decoder(PerceivedObjects),
            "humans": runtime.decoder(PerceivedHumans),
            "heartbeat": runtime.decoder(SafetyStatus),
            "route": runtime.decoder(TraceRecord),
            "safety": runtime.decoder(SafetyEvent),
            "feedback": runtime.decoder(Feedback[ExecutePlanFeedback]),  # type: ignore[misc]
            "plan": runtime.decoder(GoalStatus),
        }
        self._route_goal = runtime.decoder(SendGoal[NavigateToPoseGoal])  # type: ignore[misc]

    @property
    def topics(self) -> list[str]:
        return list(self.channels)

    # Zenoh's side: store and return.

    def receive(self, source: Inputs, key: str, payload: bytes) -> None:
        (self.logs if source.every else self.latest).put(source.kind, key, payload)

    def viewer_subscribed(self, topic: str) -> None:
        """A viewer that subscribes to the scene gets it again (the protocol keeps no last message),
        within SCENE_AGAIN."""
        if topic == scene3d.SCENE_TOPIC:
            self._static_due.set()

    # The publishing thread.

    def _log(self, topic: str, message: scene3d.Message) -> None:
        self.channels[topic].log(scene3d.encode(message))

    def _decode(self, kind: str, key: str, payload: bytes) -> Any:
        try:
            return self._decoders[kind].decode(payload)
        except DECODE_ERRORS as exc:
            if (line := self.undecodable.note(key, f"{kind}: {exc}")) is not None:
                log.warning("%s", line)
            return None

    def publish_once(self) -> None:
        now = self._clock()
        wait = SCENE_AGAIN if self._static_due.is_set() else STATIC_PERIOD
        if not 0.0 <= now - self._static_sent < wait:
            self._static_due.clear()
            self._static_sent = now
            self._log(scene3d.SCENE_TOPIC, self.scene.static(now))
        tf_changed = False
        for kind, (key, payload) in self.latest.take().items():
            message = self._decode(kind, key, payload)
            if message is None:
                continue
            if kind in PASSTHROUGH:
                self.channels[PASSTHROUGH[kind].key(self.robot)].log(payload)
            with self._showing(kind, key):
                if kind == "odom":
                    self._base = scene3d.base_transform(message)
                    tf_changed = True
                elif kind == "joints" and self.arm is not None:
                    self._arm_frames = self.arm.transforms(message)
                    tf_changed = True
                elif kind == "objects":
                    self._log(scene3d.OBJECTS_TOPIC, self.scene.objects(message))
                elif kind == "humans":
                    self._log(scene3d.PEOPLE_TOPIC, self.scene.people(message))
                elif kind == "route":
                    self._route(key, message, now)
        if tf_changed:
            frames = ([self._base] if self._base is not None else []) + self._arm_frames
            self._log(scene3d.TF_TOPIC, scene3d.FrameTransforms(transforms=frames))
        for kind, key, payload in self.logs.take():
            message = self._decode(kind, key, payload)
            if message is None:
                continue
            if kind == "plan":
                self.channels[PASSTHROUGH["plan"].key(self.robot)].log(payload)
            with self._showing(kind, key):
                if kind == "safety":
                    self._log(scene3d.LOG_TOPIC, scene3d.safety_log(message))
                elif kind == "feedback":
                    self._log(scene3d.LOG_TOPIC, scene3d.feedback_log(message.goal_id, message.feedback, now))
                elif kind == "plan":
                    self._log(scene3d.LOG_TOPIC, scene3d.plan_status_log(message, now))

    @contextmanager
    def _showing(self, kind: str, key: str) -> Iterator[None]:
        """One message made into Foxglove's. One that cannot be (a value Foxglove's message cannot
        carry, such as a stamp of -1e300) is dropped and logged: what a robot sends may not end the view."""
        try:
            yield
        except Exception as exc:  # the conversions' own errors (scene3d, pinocchio), whatever the data hit
            if (line := self.unshowable.note(key, f"{kind}: {type(exc).__name__}: {exc}")) is not None:
                log.warning("%s", line)

    def _route(self, key: str, trace: TraceRecord, now: float) -> None:
        if bytes(trace.query) == b"null" or trace.error:
            return
        try:
            request = self._route_goal.decode(bytes(trace.query))
        except DECODE_ERRORS as exc:
            if (line := self.undecodable.note(key, f"route: {exc}")) is not None:
                log.warning("%s", line)
            return
        goal: NavigateToPoseGoal = request.goal
        self._log(scene3d.ROUTE_TOPIC, scene3d.route(list(goal.path), goal.pose, now))

    def publish_camera(self, node: Node) -> None:
        """One picture from the robot's camera (a query, so not on the publishing thread)."""
        try:
            image = node.call(keys.CAMERA_IMAGE, Empty(), timeout=CAMERA_TIMEOUT)
        except CallError as exc:
            if (line := self.undecodable.note("camera", str(exc))) is not None:
                log.warning("no camera picture: %s", line)
            return
        with self._showing("camera", keys.CAMERA_IMAGE.path):
            self._log(scene3d.CAMERA_TOPIC, scene3d.camera_image(image))


class TeleopBridge:
    """Client publish to cmd/teleop/cmd_vel: the gate decides (tether/viewteleop.py), this sends and logs.

    Called on the server's threads and the deadman's; one lock around each decision and its send, so
    a stop is never overtaken by the twist decided before it. Nothing raises out of here: a bad
    message is logged (each kind of complaint once, then counted, services/repeats.py) and dropped."""

    def __init__(
        self,
        send: Callable[[Twist], None],
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.gate = TeleopGate()
        self._send, self._clock, self._wall = send, clock, wall
        self._lock = threading.Lock()
        self.refusals = RepeatLog("teleop input refused")
        # The channels taken and the stops for one gone are logged as refusals are: a client advertising
        # and unadvertising in a loop wrote a line for each, thousands a second.
        self.taken = RepeatLog("teleop channels taken")
        self.gone = RepeatLog("teleop stops for a channel gone while driving")
        # What a Foxglove user should see (the server's status messages), sent by the deadman's thread.
        self.notices: collections.deque[str] = collections.deque(maxlen=16)
        self._closed = False  # the view ends: no twist goes out any more but close()'s stop

    def _put(self, twist: Twist) -> None:
        self._send(msgspec.structs.replace(twist, stamp=self._wall()))

    def _refused(self, exc: Refused, detail: str, notify: bool = False) -> None:
        # One line per kind of problem, then a count every few seconds: a flood does not fill the log.
        if (line := self.refusals.note(type(exc).__name__, detail)) is not None:
            log.warning("%s", line)
        # Each refused channel is told to Foxglove, also the second within the log's few seconds
        # (another client's, maybe): the deque is bounded, a flood costs nothing.
        if notify:
            self.notices.append(f"tether view: {detail}")

    @staticmethod
    def _note(repeats: RepeatLog, detail: str) -> None:
        if (line := repeats.note(TELEOP_TOPIC, detail)) is not None:
            log.warning("%s", line)

    def advertise(self, client: int, channel: ClientChannel) -> None:
        try:
            self.gate.advertise(client, channel.id, channel.topic, channel.encoding, channel.schema_name)
        except Refused as exc:
            self._refused(exc, f"client {client} channel {channel.id} not taken: {exc}", notify=True)
            return
        self._note(self.taken, f"client {client} drives through channel {channel.id}")

    def message(self, client: int, channel: int, data: bytes) -> None:
        with self._lock:
            if self._closed:
                return
            try:
                accepted = self.gate.message(client, channel, data, self._clock())
            except Refused as exc:
                self._refused(exc, f"client {client} channel {channel}: {exc}")
                return
            self._put(accepted.twist)
        for axis in accepted.warn_ignored:
            log.warning("teleop: %s is ignored (the base drives on linear.x and angular.z only)", axis)

    def unadvertise(self, client: int, channel: int) -> None:
        with self._lock:
            if (stop := self.gate.unadvertise(client, channel)) is not None and not self._closed:
                self._put(stop)
                self._note(self.gone, f"client {client} channel {channel} gone while driving: stopped")

    def tick(self) -> None:
        """The deadman: a stop once the messages stopped coming."""
        with self._lock:
            if (stop := self.gate.expire(self._clock())) is not None and not self._closed:
                self._put(stop)

    def heartbeat(self, status: SafetyStatus) -> None:
        """Safety's heartbeat: a latched e-stop stops what this view drives, and what is held through
        it drives nothing until let go (tether/viewteleop.py, TeleopGate.estop)."""
        with self._lock:
            latched_now = status.estop.latched and not self.gate.rearming
            if (stop := self.gate.estop(status.estop.latched)) is not None and not self._closed:
                self._put(stop)
        if latched_now:
            self.notices.append("tether view: the e-stop latched; after its reset, let go of the buttons, then drive")

    def close(self) -> None:
        """The view ends: a moving robot is told to stop now, and every twist after this is dropped
        (the server may take messages until it stops, the deadman may have ended already)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self.gate.moving:
                self._put(Twist())


class Listener(foxglove.websocket.ServerListener):
    """The SDK's callbacks (on its own threads): a flag set, or teleop's quick decision and send.

    An exception here would only be logged by the SDK, but none is let out: the viewer keeps serving."""

    def __init__(self, view: LiveView, teleop: TeleopBridge | None = None) -> None:
        self.view = view
        self.teleop = teleop

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self.view.viewer_subscribed(channel.topic)

    def on_client_advertise(self, client: Client, channel: ClientChannel) -> None:
        if self.teleop is not None:
            self._guard(self.teleop.advertise, client.id, channel)

    def on_message_data(self, client: Client, client_channel_id: int, data: bytes) -> None:
        if self.teleop is not None:
            self._guard(self.teleop.message, client.id, client_channel_id, data)

    def on_client_unadvertise(self, client: Client, client_channel_id: int) -> None:
        # Also called for each of a client's channels when it disconnects.
        if self.teleop is not None:
            self._guard(self.teleop.unadvertise, client.id, client_channel_id)

    @staticmethod
    def _guard(call: Callable[..., None], *args: Any) -> None:
        try:
            call(*args)
        except Exception:  # a failed send (Zenoh closing): logged, the server goes on
            log.exception("teleop callback failed")


def load_scene(config: Path | None) -> tuple[scene3d.Scene, tuple[str, tuple[float, float, float]]]:
    """The world and policy safety runs with (the `[safety]` table of `config`), and the arm's URDF and mount."""
    from services.worldmodel import WorldFileError, load_world

    safety = runtime.load_config(SafetyConfig, config, "safety")
    try:
        world = load_world(world_path(safety.world))
    except WorldFileError as exc:
        raise ConfigError(str(exc)) from None
    policy = Path(safety.policy or DEFAULT_POLICY)
    try:
        separation, zones = scene3d.policy_drawn(policy.read_bytes(), policy)
    except OSError as exc:
        raise ConfigError(f"cannot read the policy file {policy}: {exc.strerror}") from None
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    mount = world.robot.arm_mount
    return scene3d.Scene(world, zones, separation), (world.robot.arm_urdf, (mount.x, mount.y, mount.z))


def fail(code: int, message: str, as_json: bool) -> typer.Exit:
    if as_json:
        print(json.dumps({"ok": False, "error": message}), flush=True)
    else:
        print(f"error: {message}", file=sys.stderr)
    return typer.Exit(code)


def view(
    ctx: typer.Context,
    port: Annotated[
        int, typer.Option(help="The WebSocket port (0: any free one, told on start).", min=0, max=65535)
    ] = DEFAULT_PORT,
    host: Annotated[str, typer.Option(help="The address to bind: loopback unless --allow-remote.")] = "127.0.0.1",
    allow_remote: Annotated[
        bool,
        typer.Option(
            "--allow-remote",
            help="Bind a non-loopback address. The protocol has no authentication: whoever reaches the port "
            "sees the robot's camera and state. Teleop from Foxglove is off then.",
        ),
    ] = False,
    config: Annotated[
        Path | None,
        typer.Option("--config", help="The stack's TOML file: its safety table names the world and policy."),
    ] = None,
    camera_rate: Annotated[
        float,
        typer.Option(
            help="Camera pictures a second while a viewer watches the camera (0: none).", min=0, max=10, callback=finite
        ),
    ] = 2.0,
    arm: Annotated[bool, typer.Option(help="The arm's links as frames (loads the arm's URDF).")] = True,
    teleop: Annotated[
        bool,
        typer.Option(
            help=f"Take Foxglove's Teleop panel on {TELEOP_TOPIC} (client publish), to cmd/teleop/cmd_vel. "
            "Off unless asked: the protocol has no authentication, and any program or web page on this "
            "computer can open a WebSocket to a loopback port. Loopback only: off when --host is not.",
        ),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object on stdout once serving.")] = False,
) -> None:
    """Serve the robot live to Foxglove (Open connection > Foxglove WebSocket > ws://127.0.0.1:8765).

    The 3D scene (walls, furniture, keep-out zones, objects, people ringed at safety's distances, the
    route), frames map -> base -> arm links, the camera, safety events and plan progress as a log.
    Layout: deploy/foxglove-layout.json.

    Teleop (with --teleop): Foxglove's Teleop panel publishing geometry_msgs/Twist on /cmd_vel drives the base
    through safety (cmd/teleop/cmd_vel, clamped as for `tether teleop`): linear.x and angular.z,
    at most 50 messages a second per client. A deadman: no message for 0.5 s, or the panel's
    channel gone, and the base is told to stop. Only when bound to loopback (client publish has no
    authentication); in a deployment run it as the operator, the only identity that may drive:
    `tether --zenoh-config DIR/ROBOT/operator.json5 --robot ROBOT view`.

    Runs until Ctrl-C. With --json: one object once serving, {"ok", "url", "port", "robot", "topics",
    "teleop"} (teleop: the topic taken, or null), or {"ok": false, "error"}.

    Exit codes: 0 stopped by Ctrl-C, SIGTERM or SIGHUP (its terminal closed), 1 the port cannot be served,
    2 bad option or config, 3 no Zenoh session.
    """
    settings: NodeSettings = ctx.obj
    if host not in LOOPBACK and not allow_remote:
        raise fail(
            EXIT_USAGE,
            f"--host {host}: the view binds to loopback only unless --allow-remote (the Foxglove WebSocket "
            "protocol has no authentication: whoever reaches the port sees the robot's camera and state)",
            as_json,
        )
    try:
        scene, (arm_urdf, mount) = load_scene(config)
    except ConfigError as exc:
        raise fail(EXIT_USAGE, str(exc), as_json) from None
    runtime.configure_logging("WARNING")
    throttle = Throttle()
    for handler in logging.getLogger().handlers:
        handler.addFilter(throttle)
    arm_frames = None
    if arm:
        try:
            arm_frames = ArmFrames(arm_urdf, mount)
        except Exception as exc:  # a URDF pinocchio cannot read: the base alone is shown
            log.warning("arm links not shown: %s", exc)
    # Its terminal closed ends it as Ctrl-C does: by default SIGHUP killed it, and a robot the Teleop
    # panel drove went on with the last twist, no stop sent.
    stop = runtime.stop_event(hangup=True)
    context = foxglove.Context()
    live = LiveView(settings.robot, scene, context, arm_frames)
    teleop_off = None
    if not teleop:
        teleop_off = "not asked for (--teleop)"
    elif host not in LOOPBACK:
        teleop_off = f"--host {host} is not loopback, and client publish has no authentication"
    try:
        node = Node("view", settings)
    except Exception as exc:  # zenoh.ZError: no router, refused login
        raise fail(EXIT_UNREACHABLE, f"cannot open a Zenoh session: {exc}", as_json) from None
    stopped = True
    with node:
        bridge = None if teleop_off else TeleopBridge(node.publisher(keys.TELEOP_CMD_VEL).put)
        if bridge is not None:
            node.subscribe(keys.HEARTBEAT, bridge.heartbeat, verify=signature_shaped)
        try:
            server = foxglove.start_server(
                name=f"tether {settings.robot}",
                host=host,
                port=port,
                context=context,
                server_listener=Listener(live, bridge),
                capabilities=[Capability.ClientPublish] if bridge else None,
                supported_encodings=["json"] if bridge else None,
                message_backlog_size=CLIENT_BACKLOG,
            )
        except Exception as exc:  # the port taken, the address not ours
            raise fail(EXIT_SERVE, f"cannot serve on {host}:{port}: {exc}", as_json) from None
        helpers: list[threading.Thread] = []

        def start_helper(name: str, target: Callable[..., None], *args: object) -> None:
            helper = threading.Thread(target=target, args=args, name=name, daemon=True)
            helper.start()
            helpers.append(helper)

        try:
            if bridge is not None:
                start_helper("view-teleop", teleop_loop, bridge, server, stop)
            for source in inputs(settings.robot):
                node.subscribe_raw(source.key_expr, lambda key, payload, s=source: live.receive(s, key, payload))
            start_helper("view-camera", camera_loop, live, node, camera_rate, stop)
            # An IPv6 address is bracketed in a URL: ws://::1:8765 is no address Foxglove can open.
            url = f"ws://{f'[{host}]' if ':' in host else host}:{server.port}"
            if as_json:
                started = {
                    "ok": True,
                    "url": url,
                    "port": server.port,
                    "robot": settings.robot,
                    "topics": live.topics,
                    "teleop": TELEOP_TOPIC if bridge else None,
                }
                print(json.dumps(started))
                sys.stdout.flush()
            else:
                print(f"Foxglove: open a Foxglove WebSocket connection to {url} (Ctrl-C stops)", file=sys.stderr)
            if bridge is not None:
                print(f"teleop: Foxglove's Teleop panel on {TELEOP_TOPIC} drives (through safety)", file=sys.stderr)
            elif teleop:
                print(f"teleop from Foxglove is off: {teleop_off}", file=sys.stderr)
            while not stop.wait(PUBLISH_PERIOD):
                live.publish_once()
        finally:
            stopped = shut_down(bridge, stop, helpers, server)
    if not stopped:
        # A thread is still in the server's stop (Rust): Python's finalization would abort the process
        # (tether/runservice.py, leave). The session is closed; the port goes with the process.
        leave(0)


def shut_down(
    bridge: TeleopBridge | None,
    stop: threading.Event,
    helpers: list[threading.Thread],
    server: foxglove.WebSocketServer,
) -> bool:
    """The view's end. Teleop first: from here no twist goes out and a moving robot is told to stop,
    before the wait for the helpers (the camera's may be in a call for seconds, and the deadman's
    thread ends with `stop`). The helpers end before the server and the session do, and before
    Python finalizes: one still in a Zenoh or Foxglove call then (both Rust) would abort the process
    as it exits (tether/runservice.py, leave). Whether the server stopped (stop_server)."""
    try:
        if bridge is not None:
            bridge.close()
    finally:
        stop.set()
        for helper in helpers:
            helper.join(timeout=HELPER_JOIN)
        stopped = stop_server(server)
    return stopped


def stop_server(server: foxglove.WebSocketServer, wait: float = SERVER_STOP_WAIT) -> bool:
    """The server stopped, waited for `wait` seconds at most: False while it still waits for a viewer
    that does not read (its connection full), which it would do for good."""
    stopping = threading.Thread(target=server.stop, name="view-stop", daemon=True)
    stopping.start()
    stopping.join(wait)
    if stopping.is_alive():
        log.warning("a viewer takes nothing of what was sent to it: the view stops without waiting for it")
        return False
    return True


def teleop_loop(bridge: TeleopBridge, server: foxglove.WebSocketServer, stop: threading.Event) -> None:
    """The deadman's clock, and the notices for Foxglove users (sent here, not in the SDK's callbacks)."""
    told = -math.inf
    while not stop.wait(TELEOP_TICK):
        try:
            bridge.tick()
            now = time.monotonic()
            if bridge.notices and now - told >= NOTICE_PERIOD:
                told = now
                pending = [bridge.notices.popleft() for _ in range(len(bridge.notices))]
                server.publish_status("\n".join(pending), StatusLevel.Warning)
        except Exception:  # a failed send: logged, the deadman keeps looking
            log.exception("teleop deadman")


def camera_loop(live: LiveView, node: Node, rate: float, stop: threading.Event) -> None:
    """Pictures at `rate` while a viewer subscribes to the camera; none when nobody looks."""
    if rate <= 0:
        return
    channel = live.channels[scene3d.CAMERA_TOPIC]
    while not stop.wait(1.0 / rate):
        if channel.has_sinks():
            live.publish_camera(node)
