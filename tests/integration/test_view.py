"""`tether view` on a real stack, seen through Foxglove's own WebSocket client, and the recording's Foxglove channels.

One stack (sim, safety, recorder) and one `tether view` for the module. The client is
@foxglove/ws-protocol's FoxgloveClient under node (tests/integration/foxglove_client, installed
with `npm ci` once into a cache folder); every message it decodes is checked against the official
JSON Schemas of @foxglove/schemas, which it prints first. The same client publishes twists as
Foxglove's Teleop panel does, and the robot drives through safety.
"""

from __future__ import annotations

import base64
import itertools
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from mcap.reader import make_reader

from bench.viewer import ViewerMissing
from bench.viewer import client_script as install_client
from schemas import keys
from schemas.common import Pose2D
from schemas.robot import NavigateToPoseGoal, Odometry, Twist
from schemas.safety import Decision, Rule, SafetyEvent
from services.actionlib import ActionClient
from services.recorder import scene3d
from services.recorder.reader import read_recording
from services.runtime import DUMP_STACKS
from tests.integration.conftest import Stack, dump_logs, start_stack, stop_stack
from tether.viewteleop import BURST, DEADMAN, RATE_HZ, TELEOP_TOPIC

DEADLINE = 60.0
FOXGLOVE_TOPICS = {
    scene3d.SCENE_TOPIC: "foxglove.SceneUpdate",
    scene3d.OBJECTS_TOPIC: "foxglove.SceneUpdate",
    scene3d.PEOPLE_TOPIC: "foxglove.SceneUpdate",
    scene3d.ROUTE_TOPIC: "foxglove.SceneUpdate",
    scene3d.TF_TOPIC: "foxglove.FrameTransforms",
    scene3d.CAMERA_TOPIC: "foxglove.CompressedImage",
    scene3d.LOG_TOPIC: "foxglove.Log",
}


def client_script() -> Path:
    """The client and its node_modules in a cache folder named by the hash of its files (installed once,
    bench/viewer.py); skipped without node and npm."""
    try:
        return install_client()
    except ViewerMissing as exc:
        pytest.skip(str(exc))


@dataclass
class Client:
    """A running client; its JSON lines as they arrive."""

    proc: subprocess.Popen[str]
    lines: list[dict[str, Any]] = field(default_factory=list)
    # Every line it wrote has been read: its stdout ended. Not when the process ends: lines it wrote
    # before exiting may still be in the pipe, waiting for a reader a loaded machine holds up.
    ended: bool = False
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _reader: threading.Thread = field(init=False)

    @classmethod
    def start(cls, script: Path, *args: str, stdin: bool = False) -> Client:
        proc = subprocess.Popen(
            ["node", str(script), *args],
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            text=True,
        )
        client = cls(proc)
        client._reader = threading.Thread(target=client._read, daemon=True)
        client._reader.start()
        return client

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._cond:
                self.lines.append(json.loads(line))
                self._cond.notify_all()
        with self._cond:
            self.ended = True
            self._cond.notify_all()

    def wait_for(self, test: Any, timeout: float = DEADLINE) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not test(self.lines):
                left = deadline - time.monotonic()
                if left <= 0 or self.ended:
                    return bool(test(self.lines))
                self._cond.wait(min(left, 0.5))
        return True

    def step(self, op: str, expect: str, timeout: float = 20.0, **args: Any) -> dict[str, Any]:
        """One step of the teleop mode, and the line that answers it (it has the key `expect`)."""
        assert self.proc.stdin is not None
        seen = len(self.lines)
        self.proc.stdin.write(json.dumps({"op": op, **args}) + "\n")
        self.proc.stdin.flush()
        assert self.wait_for(lambda lines: any(expect in line for line in lines[seen:]), timeout), self.lines[seen:]
        return next(line for line in self.lines[seen:] if expect in line)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=10)
        self._reader.join(timeout=10)
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None:
                stream.close()

    def messages(self, topic: str) -> list[dict[str, Any]]:
        return [line["message"] for line in self.lines if line.get("topic") == topic and "message" in line]

    @property
    def channels(self) -> dict[str, dict[str, Any]]:
        return {line["channel"]["topic"]: line["channel"] for line in self.lines if "channel" in line}


@contextmanager
def running_view(stack: Stack, args: list[str], log: Path) -> Iterator[tuple[subprocess.Popen[str], dict[str, Any]]]:
    """`tether view --json` on the stack's config, its stderr in `log`: the process and the line it
    started with. Stopped with SIGINT at the end (exit 0 expected), killed if the test failed first."""
    command = [sys.executable, "-m", "tether", "view", "--json", *args, "--config", str(stack.tmp / "tether.toml")]
    with log.open("w") as log_file:
        view = subprocess.Popen(
            command,
            env=stack.supervisor.env(),
            stdout=subprocess.PIPE,
            stderr=log_file,
            text=True,
            start_new_session=True,
        )
    try:
        assert view.stdout is not None
        started = json.loads(view.stdout.readline() or "{}")
        assert started.get("ok"), f"tether view did not start: {started}\n{log.read_text()}"
        yield view, started
        os.killpg(view.pid, signal.SIGINT)
        assert view.wait(timeout=20) == 0
    finally:
        if view.poll() is None:
            # Its threads' stacks into its log first (faulthandler, as a service's: runtime.DUMP_STACKS),
            # for the teardown's print of the log to say where it hung.
            os.kill(view.pid, DUMP_STACKS)
            deadline = time.monotonic() + 5.0
            while "most recent call first" not in log.read_text(errors="replace") and time.monotonic() < deadline:
                time.sleep(0.05)
            os.killpg(view.pid, signal.SIGKILL)
            view.wait(timeout=10)
        assert view.stdout is not None
        view.stdout.close()


@dataclass
class Viewed:
    stack: Stack
    view: subprocess.Popen[str]
    url: str
    script: Path
    official: dict[str, Any]
    log: Path


@pytest.fixture(scope="module")
def viewed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Viewed]:
    script = client_script()
    schemas = subprocess.run(["node", str(script), "schemas"], capture_output=True, text=True, timeout=60, check=True)
    official = json.loads(schemas.stdout.splitlines()[0])["official"]
    tmp = tmp_path_factory.mktemp("view")
    stack = start_stack(tmp, 4.0, services=("sim", "safety", "recorder"))
    try:
        with running_view(stack, ["--teleop", "--port", "0"], tmp / "view.log") as (view, started):
            assert started["teleop"] == TELEOP_TOPIC
            yield Viewed(stack, view, started["url"], script, official, tmp / "view.log")
            assert view.poll() is None, "tether view died"
    finally:
        print("----- view log -----\n" + (tmp / "view.log").read_text()[-5000:])
        stop_stack(stack)


def ring_radii(entity: dict[str, Any]) -> list[float]:
    """The radius of each line loop of an entity, from its centre."""
    radii = []
    for line in entity["lines"]:
        xs, ys = [p["x"] for p in line["points"]], [p["y"] for p in line["points"]]
        cx, cy = sum(xs) / len(xs), sum(ys) / len(ys)
        radii.append(round(math.hypot(xs[0] - cx, ys[0] - cy), 3))
    return sorted(radii)


def test_foxglove_client_gets_the_scene_frames_camera_route_and_log(viewed: Viewed) -> None:
    robot = viewed.stack.settings.robot
    client = Client.start(viewed.script, "watch", viewed.url, str(DEADLINE), *FOXGLOVE_TOPICS)
    try:
        assert client.wait_for(lambda lines: sum("channel" in line for line in lines) >= len(FOXGLOVE_TOPICS) + 3)
        # A short drive with a route: safety approves it (a log line), the robot gets it (the route).
        goal = NavigateToPoseGoal(pose=Pose2D(x=6.6, y=1.2), path=[Pose2D(x=6.3, y=1.2)])
        ActionClient(viewed.stack.node, keys.CMD_NAVIGATE).send(goal)  # raises if safety refuses it
        assert client.wait_for(lambda lines: any(line.get("done") for line in lines)), client.lines[-5:]
    finally:
        client.close()
    assert {"done": "all"} in client.lines, [line for line in client.lines if "message" not in line]

    channels = client.channels
    for topic, name in FOXGLOVE_TOPICS.items():
        channel = channels[topic]
        assert (channel["schemaName"], channel["schemaEncoding"], channel["encoding"]) == (name, "jsonschema", "json")
        assert json.loads(channel["schema"])["type"] == "object"
    # tether's own messages as they are, for plots: the same topics as in a recording.
    assert channels[keys.ODOM.key(robot)]["schemaName"] == "Odometry"
    assert channels[keys.HEARTBEAT.key(robot)]["schemaName"] == "SafetyStatus"
    for topic, name in FOXGLOVE_TOPICS.items():
        arrived = client.messages(topic)
        assert arrived, f"nothing on {topic}"
        for message in arrived:
            jsonschema.validate(message, viewed.official[name])  # Foxglove's own schema, not ours

    scene = {e["id"]: e for e in client.messages(scene3d.SCENE_TOPIC)[0]["entities"]}
    assert {"walls", "furniture/kitchen_counter", "keep_out/stairs", "robot/base", "room/kitchen"} <= set(scene)
    assert len(scene["walls"]["cubes"]) >= 4 and scene["robot/base"]["frame_id"] == "base"
    people = {e["id"]: e for e in client.messages(scene3d.PEOPLE_TOPIC)[0]["entities"]}
    # The default policy: a person 0.2 m around, stop within 0.2 m of the body, slow within 1.5 m.
    assert ring_radii(people["person/operator"]) == [0.4, 1.7]
    objects = {e["id"] for e in client.messages(scene3d.OBJECTS_TOPIC)[0]["entities"]}
    assert "object/blue_book" in objects
    route = client.messages(scene3d.ROUTE_TOPIC)[0]["entities"][0]["lines"][0]["points"]
    assert [(p["x"], p["y"]) for p in route] == [(6.3, 1.2), (6.6, 1.2)]
    frames = {t["child_frame_id"]: t for t in client.messages(scene3d.TF_TOPIC)[0]["transforms"]}
    assert frames["base"]["parent_frame_id"] == "map"
    assert {"panda_link0", "panda_hand", "panda_leftfinger"} <= set(frames)
    image = client.messages(scene3d.CAMERA_TOPIC)[0]
    assert image["format"] == "png" and base64.b64decode(image["data"])[:8] == b"\x89PNG\r\n\x1a\n"
    assert any(m["name"] == "safety" and "navigate_to_pose" in m["message"] for m in client.messages(scene3d.LOG_TOPIC))


def test_a_hostile_client_neither_stops_the_view_nor_holds_up_safety(viewed: Viewed) -> None:
    beats: list[float] = []
    subscription = viewed.stack.node.subscribe(keys.HEARTBEAT, lambda s: beats.append(time.monotonic()))
    hostile = Client.start(viewed.script, "hostile", viewed.url, "5")
    try:
        assert hostile.wait_for(lambda lines: any(line.get("done") for line in lines), 30.0)
    finally:
        hostile.close()
        subscription.undeclare()
    subscribed = next(line for line in hostile.lines if "subscribed" in line)
    # The server read the garbage and said what was wrong with it, then took 50 subscriptions per channel.
    assert len(subscribed["answers"]["statuses"]) >= 5, subscribed
    assert subscribed["subscribed"] >= 50 * len(FOXGLOVE_TOPICS)
    assert viewed.view.poll() is None, "tether view died"
    # Safety's heartbeat went on while the client sent garbage and then stopped reading.
    gaps = [b - a for a, b in itertools.pairwise(beats)]
    assert len(beats) > 20 and max(gaps) < 1.0, f"{len(beats)} heartbeats, longest gap {max(gaps, default=0):.2f} s"
    # And the view still serves a well-behaved viewer.
    client = Client.start(viewed.script, "watch", viewed.url, "30", scene3d.SCENE_TOPIC, scene3d.TF_TOPIC)
    try:
        assert client.wait_for(lambda lines: any(line.get("done") for line in lines), 40.0)
    finally:
        client.close()
    assert {"done": "all"} in client.lines


class Heard:
    """What one key carried, each message with its arrival time (Unix seconds)."""

    def __init__(self) -> None:
        self.items: list[tuple[float, Any]] = []
        self._cond = threading.Condition()

    def __call__(self, message: Any) -> None:
        with self._cond:
            self.items.append((time.time(), message))
            self._cond.notify_all()

    def first(self, test: Any, timeout: float = 10.0) -> tuple[float, Any]:
        """The first (arrival, message) that passes `test`, waiting for it up to `timeout` seconds."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                found = next(((at, m) for at, m in self.items if test(at, m)), None)
                left = deadline - time.monotonic()
                if found is not None or left <= 0:
                    assert found is not None, f"not heard within {timeout} s; the last: {self.items[-3:]}"
                    return found
                self._cond.wait(min(left, 0.5))


def twist(lx: float = 0.0, az: float = 0.0) -> dict[str, dict[str, float]]:
    return {"linear": {"x": lx, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": az}}


# Bounds a halt in wall seconds (the deadman): with the realtime tests, at normal priority.
@pytest.mark.realtime
def test_foxglove_teleop_drives_through_safety_and_the_deadman_stops_it(viewed: Viewed) -> None:
    node = viewed.stack.node
    odom, teleop, events = Heard(), Heard(), Heard()

    def on_event(event: SafetyEvent) -> None:
        # What reached safety on cmd/teleop/cmd_vel (each twist is decided and reported), as sent.
        events(event)
        if event.key == keys.TELEOP_CMD_VEL.path and "requested_mps" in event.values:
            teleop(Twist(linear_x=event.values["requested_mps"], angular_z=event.values["requested_rps"]))

    subscriptions = [node.subscribe(keys.ODOM, odom), node.subscribe(keys.SAFETY_EVENTS, on_event)]
    client = Client.start(viewed.script, "teleop", viewed.url, "120", stdin=True)
    try:
        assert client.wait_for(lambda lines: any("serverInfo" in line for line in lines), 20.0), client.lines
        info = next(line["serverInfo"] for line in client.lines if "serverInfo" in line)
        assert "clientPublish" in info["capabilities"] and info["supportedEncodings"] == ["json"]

        def still(at: float, o: Odometry) -> bool:
            return abs(o.linear_x) < 0.01 and abs(o.angular_z) < 0.01

        # The base stands still first (the first test's drive has ended).
        odom.first(lambda at, o: still(at, o) and at > time.time() - 0.2, 20.0)

        # A channel on another topic is refused, and the Foxglove user is told why.
        twist_type: dict[str, Any] = {"encoding": "json", "schemaName": "geometry_msgs/Twist"}
        other = client.step("advertise", "advertised", topic="/other", **twist_type)["advertised"]
        assert client.wait_for(lambda lines: any("/other" in str(line.get("status")) for line in lines), 10.0)
        channel = client.step("advertise", "advertised", topic=TELEOP_TOPIC, **twist_type)["advertised"]
        # Garbage, a NaN-ish number, a string, an absurd speed, and a twist on the refused channel.
        for text in ("not json", '{"linear":{"x":1e999}}', '{"linear":{"x":"fast"}}', '{"linear":{"x":1e6}}'):
            client.step("raw", "raw", channel=channel, text=text)
        client.step("raw", "raw", channel=other, text=json.dumps(twist(0.5)))
        start = odom.items[-1][1]

        # The panel's forward button held 1.5 s at 10 Hz: the view, still serving, passes each on.
        client.step("publish", "published", timeout=30.0, channel=channel, message=twist(0.1), hz=10, seconds=1.5)
        driven = [(at, t) for at, t in teleop.items if t.linear_x != 0.0]
        assert teleop.items[0][1].linear_x == 0.1, "something of the refused input reached the robot"
        assert len(driven) >= 12 and all(t == Twist(linear_x=0.1) for _, t in driven)
        last_driven = driven[-1][0]
        # The deadman: the view's stop, DEADMAN after the last twist, and the base standing soon after.
        stop_at, _ = teleop.first(lambda at, t: at > last_driven and t.linear_x == 0.0 and t.angular_z == 0.0)
        assert DEADMAN - 0.05 <= stop_at - last_driven <= DEADMAN + 0.25, stop_at - last_driven
        stood_at, stood = odom.first(lambda at, o: at > last_driven and still(at, o))
        assert stood_at - last_driven <= DEADMAN + 0.4, stood_at - last_driven
        moved = math.hypot(stood.pose.x - start.pose.x, stood.pose.y - start.pose.y)
        assert 0.2 < moved < 2.0, f"moved {moved:.2f} m from {start.pose} to {stood.pose}"

        # A flood: a burst of the client's budget is passed on, the rest dropped.
        flood_from = time.time()
        client.step("burst", "burst", channel=channel, message=twist(), count=500)
        # Over the speed limit, held 0.6 s: safety clamps it and says so; then the panel's channel goes
        # away (as when the panel closes or Foxglove disconnects): a stop at once, not after the deadman.
        client.step("publish", "published", channel=channel, message=twist(-5.0), hz=10, seconds=0.6)
        client.step("unadvertise", "unadvertised", channel=channel)
        fast = [(at, t) for at, t in teleop.items if t.linear_x == -5.0]
        flooded = [at for at, t in teleop.items if flood_from < at < fast[0][0]]
        # The bucket's own bound: its burst, and what it refilled while the flood arrived (a loaded
        # machine spreads the 500 messages out); nowhere near all 500.
        spread = flooded[-1] - flooded[0] if flooded else 0.0
        assert 1 <= len(flooded) <= BURST + RATE_HZ * spread + 3, (len(flooded), spread)
        assert len(flooded) < 100, len(flooded)
        gone_at, _ = teleop.first(lambda at, t: at > fast[-1][0] and t.linear_x == 0.0)
        assert gone_at - fast[-1][0] < DEADMAN - 0.15, gone_at - fast[-1][0]
        _, clamp = events.first(
            lambda at, e: e.key == keys.TELEOP_CMD_VEL.path and e.values.get("requested_mps") == -5.0
        )
        assert (clamp.decision, clamp.rule) == (Decision.CLAMPED, Rule.BASE_SPEED), clamp
        assert -0.6 <= clamp.values["speed_mps"] < 0.0
        client.step("close", "done")
    finally:
        client.close()
        for subscription in subscriptions:
            subscription.undeclare()
    assert viewed.view.poll() is None, "tether view died"
    log = viewed.log.read_text()
    for reason in (
        "not taken: topic '/other'",
        "not a geometry_msgs/Twist in JSON",
        f"channel {other} was not taken",
        "more than 50 messages a second from this client: dropped",
        "gone while driving: stopped",
    ):
        assert reason in log, reason


def test_teleop_is_off_when_the_view_binds_beyond_loopback(viewed: Viewed) -> None:
    stack = viewed.stack
    events = Heard()
    subscription = stack.node.subscribe(keys.SAFETY_EVENTS, events)
    args = [
        "--teleop",
        "--host",
        "0.0.0.0",
        "--allow-remote",
        "--port",
        "0",
        "--json",
        "--no-arm",
        "--camera-rate",
        "0",
    ]
    view = subprocess.Popen(
        [sys.executable, "-m", "tether", "view", *args, "--config", str(stack.tmp / "tether.toml")],
        env=stack.supervisor.env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    client = None
    try:
        assert view.stdout is not None and view.stderr is not None
        started = json.loads(view.stdout.readline() or "{}")
        assert started.get("ok") and started["teleop"] is None, started
        client = Client.start(viewed.script, "teleop", f"ws://127.0.0.1:{started['port']}", "60", stdin=True)
        assert client.wait_for(lambda lines: any("serverInfo" in line for line in lines), 20.0), client.lines
        info = next(line["serverInfo"] for line in client.lines if "serverInfo" in line)
        assert "clientPublish" not in info["capabilities"]
        channel = client.step("advertise", "advertised", topic=TELEOP_TOPIC, encoding="json", schemaName="x")
        client.step("publish", "published", channel=channel["advertised"], message=twist(0.2), hz=10, seconds=0.5)
        client.step("close", "done")
        os.killpg(view.pid, signal.SIGINT)
        assert view.wait(timeout=20) == 0
        assert "teleop from Foxglove is off: --host 0.0.0.0 is not loopback" in view.stderr.read()
        # Nothing of it reached safety (each twist there is decided and reported on safety/events).
        assert not [e for _, e in events.items if e.key == keys.TELEOP_CMD_VEL.path]
    finally:
        subscription.undeclare()
        if client is not None:
            client.close()
        if view.poll() is None:
            os.killpg(view.pid, signal.SIGKILL)
            view.wait(timeout=10)
        for stream in (view.stdout, view.stderr):
            if stream is not None:
                stream.close()


def test_the_recording_carries_the_scene_frames_and_log_for_foxglove(viewed: Viewed) -> None:
    stack = viewed.stack
    robot = stack.settings.robot
    try:
        assert stack.supervisor.stop("recorder") == 0
    except BaseException:
        dump_logs(stack.supervisor, ("recorder",))
        raise
    [path] = sorted(stack.recordings.glob("*.mcap"))
    odom_key = keys.ODOM.key(robot)
    odometry: dict[int, bytes] = {}
    derived: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    names: dict[str, tuple[str, str, str]] = {}
    with path.open("rb") as f:
        for schema, channel, record in make_reader(f).iter_messages(log_time_order=True):
            if channel.topic == odom_key:
                odometry[record.log_time] = record.data
            elif scene3d.is_derived(channel.topic):
                assert schema is not None, channel.topic
                names[channel.topic] = (schema.name, schema.encoding, channel.message_encoding)
                derived.setdefault(channel.topic, []).append((record.log_time, json.loads(record.data)))
    assert names[scene3d.SCENE_TOPIC] == ("foxglove.SceneUpdate", "jsonschema", "json")
    assert names[scene3d.TF_TOPIC] == ("foxglove.FrameTransforms", "jsonschema", "json")
    assert names[scene3d.LOG_TOPIC] == ("foxglove.Log", "jsonschema", "json")
    [(_, static)] = derived[scene3d.SCENE_TOPIC]
    jsonschema.validate(static, viewed.official["foxglove.SceneUpdate"])
    assert {"walls", "keep_out/stairs", "furniture/coffee_table"} <= {e["id"] for e in static["entities"]}
    # One map -> base frame for each odometry message, at its time and where it put the base.
    frames = derived[scene3d.TF_TOPIC]
    assert len(frames) == len(odometry) > 10
    for log_time, message in frames[:: max(1, len(frames) // 20)]:
        jsonschema.validate(message, viewed.official["foxglove.FrameTransforms"])
        [frame] = message["transforms"]
        pose = json.loads(odometry[log_time])["pose"]
        assert (frame["translation"]["x"], frame["translation"]["y"]) == (pose["x"], pose["y"])
        assert math.isclose(2 * math.atan2(frame["rotation"]["z"], frame["rotation"]["w"]), pose["yaw"], abs_tol=1e-9)
    for _, message in derived[scene3d.LOG_TOPIC]:
        jsonschema.validate(message, viewed.official["foxglove.Log"])
    # tether's own reader keeps them apart: replay and recheck see the traffic only.
    recording = read_recording(path)
    assert not any(scene3d.is_derived(m.key) for m in recording.messages)
    assert len(recording.derived) == sum(len(v) for v in derived.values())
