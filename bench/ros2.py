"""cmd_vel at 1 kHz and navigate goals through safety and the ros2 backend to a ROS 2 robot, vs the native sim path.

    python -m bench.ros2 --json        one JSON object on stdout, progress on stderr
    python -m bench.ros2               a short table

Two stacks, one after the other, real processes started by the Supervisor on robot names and ports
of their own: `ros2` (safety, the ros2 backend and the stand-in robot ros2sim, the pybullet sim
behind a ROS 2 face on rmw_zenoh keys, on a loopback Zenoh network of its own that the backend joins
at `[ros2] endpoint`), then `native` (safety and the sim on tether's keys): one stack at a time, as
deployed, so neither waits for the CPU on the other's account. Both sims run at real time and report
odometry at 500 Hz; the backend passes every report on. This process joins the robot's network as
the ROS 2 node `tether_bench` (services/ros2/rmw.py RosNode), a Zenoh peer listening on a port of its
own, so the backend connects to it as it does to the stand-in: what arrives here arrives as there.

Navigate goals, on each stack: `--warmup` goals not counted, then `--trials`, each on
`cmd/navigate_to_pose` (through safety, as the executor sends them): 0.3 m east along the
household's corridor from the start pose (6.0, 1.2), then back (driven backwards), in turn. Each is
sent with the base standing still (|linear_x| and |angular_z| below 0.01) and must succeed. From
t0 = time.time() just before send_goal: `accepted`, the accepting reply arriving here; `robot`, the
robot's own action server accepting the goal, by the robot's stamp (the sim: the ACCEPTED GoalStatus
on robot/navigate_to_pose; the stand-in: the GoalInfo stamp of the NavigateToPose goal the backend
sent it, in its GoalStatusArray); `motion`, the first odometry sample, by the robot's stamp, with
|linear_x| or |angular_z| above 0.01 (the sims step physics at 240 Hz: resolved to about 4 ms).

cmd_vel, on the ros2 stack after its goals: `Twist(angular_z, stamp=time.time())` on `cmd/cmd_vel`
at a steady rate (default 1 kHz for 10 s, paced as bench.stream), turning in place, each twist told
apart by its angular_z (0.3 rad/s plus a millionth per twist, which safety and the backend pass on
unchanged). For the same twists, latency = arrival here - stamp on two paths: `native` at
robot/cmd_vel (what safety sends: what the sim would get) and `ros2` at the robot's ROS 2 `cmd_vel`
(the geometry_msgs/msg/Twist the backend makes of it; its arrival taken once rmw.py has checked the
key and attachment and decoded the CDR, a few microseconds). `lost` = sent - received on each path;
a twist safety vetoes counts as lost (vetoes counted from safety/events).

Baselines: the native paths, in the same run. `added_*` = ros2 - native, of the p50s and of the p99s
(cmd_vel; `goal_*_added_p50_ms` for goals); `hop_*`: ros2 arrival - native arrival of each twist,
the backend's hop alone. Goals: nothing lost, added p50 at most 0.5 ms (cmd_vel, and a goal at the
robot).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import statistics
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import zenoh

from bench.service import (
    STILL,
    TOKEN_ENV,
    BenchError,
    Heartbeats,
    Latest,
    Stack,
    base_speed,
    bench_main,
    bench_settings,
    bounded,
    measured,
    ms_summary,
    notes,
    print_rows,
    reporter,
    running_stack,
    show,
    wait_until,
)
from bench.stream import Vetoes, paced
from schemas import keys
from schemas.actions import GoalState, GoalStatus
from schemas.common import Pose2D
from schemas.robot import NavigateToPoseGoal, Odometry, Twist
from services import runtime
from services.actionlib import ActionClient
from services.errors import CallError, GoalRejected
from services.ros2.backend import TWIST, to_seconds
from services.ros2.config import Ros2Config
from services.ros2.node import naming, robot_session_config
from services.ros2.rmw import RosNode
from services.ros2.types import RosTypes
from services.ros2.wire import GOAL_STATUS_ARRAY_TYPE, STATUS_QOS
from services.runtime import ALL_SERVICES, ROBOT_BACKENDS, Node, NodeSettings
from services.worldmodel import load_world
from tether.supervisor import free_base_port

PROG = "bench.ros2"
GOALS = {"goal_added_p50_ms": 0.5}
SIM = {"realtime_factor": 1.0, "odom_hz": 500.0}
# The backend's own rate limit on the reports it passes on: above the sim's, so it passes them all.
ROS2 = {"odom_hz": 1000.0}
BENCH_NODE = "tether_bench"
TURN = 0.3  # rad/s
STEP = 1e-6  # rad/s between consecutive twists
LEG = 0.3  # metres east and back
WARMUP_HZ = 20.0
DRAIN = 0.5  # seconds to wait for the last twists after the stream ends
READY_TIMEOUT = 10.0
STILL_TIMEOUT = 5.0
MOVE_TIMEOUT = 5.0
GOAL_TIMEOUT = 5.0
RESULT_TIMEOUT = 30.0
progress = reporter(PROG)


# The stacks


def stack_settings() -> tuple[NodeSettings, str, str, NodeSettings]:
    """(the ros2 stack's settings, its robot's ROS 2 endpoint, this process's endpoint on the robot's
    network, the native stack's settings): one block of free loopback ports, so no service and no
    robot network finds another stack's."""
    settings = bench_settings("ros2")
    span = len(ALL_SERVICES)
    base = settings.base_port if os.environ.get("TETHER_BASE_PORT") else free_base_port(2 * span + 2)
    ros2 = dataclasses.replace(settings, base_port=base)
    native = dataclasses.replace(settings, robot=f"{settings.robot}-native", base_port=base + span + 2)
    return ros2, f"tcp/{settings.host}:{base + span}", f"tcp/{settings.host}:{base + span + 1}", native


@contextlib.contextmanager
def robot_stack(
    robot: tuple[str, ...], settings: NodeSettings, tmp: Path, config: dict[str, dict[str, Any]]
) -> Iterator[Stack]:
    """The `robot` services and safety, once safety beats with the e-stop clear; the config file, operator
    token, e-stop state file and logs in a directory of the stack's own."""
    home = tmp / settings.robot
    home.mkdir()
    token = home / "operator-token"
    safety = {"operator_token_file": str(token), "estop_state_file": str(home / "estop-state.json")}
    progress(f"starting {', '.join(robot)} and safety (robot {settings.robot}, base port {settings.base_port})")
    with running_stack(
        (*robot, "safety"),
        settings,
        home,
        progress,
        config={"sim": SIM, "safety": safety, **config},
        env={TOKEN_ENV: str(token)},
    ) as stack:
        stack.token_file = token
        Heartbeats(stack.node).wait_clear(READY_TIMEOUT)
        yield stack


@contextlib.contextmanager
def robot_network(endpoint: str, listen: str) -> Iterator[RosNode]:
    """This process as a ROS 2 node on the robot's own Zenoh network, joined as the backend joins it,
    and listening on `listen`: the stand-in is a Zenoh peer, not a router, so it routes nothing from
    the backend to a third peer; the backend hears of this one from it (gossip) and connects here."""
    config = Ros2Config(endpoint=endpoint)
    conf = robot_session_config(config)
    conf.insert_json5("listen/endpoints", json.dumps([listen]))
    with (
        zenoh.open(conf) as session,
        RosNode(session, RosTypes(config.distro), naming(config), BENCH_NODE) as ros,
    ):
        yield ros


# Navigate goals


class GoalPath:
    """navigate_to_pose on one stack, seen from here: goals sent through safety, the robot's stamps
    of accepting goals, and the first odometry sample moving after t0."""

    def __init__(self, name: str, node: Node) -> None:
        self.name = name
        self.client = ActionClient(node, keys.CMD_NAVIGATE)
        self.accepted_ms: list[float] = []
        self.robot_ms: list[float] = []
        self.motion_ms: list[float] = []
        self._lock = threading.Lock()
        self._robot_accepts: set[float] = set()
        self._t0 = math.inf
        self._moved: float | None = None
        self.odom = Latest(node, keys.ODOM, self._on_odom)

    def robot_accepted(self, stamp: float) -> None:
        with self._lock:
            self._robot_accepts.add(stamp)

    def _on_odom(self, odom: Odometry) -> None:
        with self._lock:
            if self._moved is None and odom.stamp >= self._t0 and base_speed(odom) > STILL:
                self._moved = odom.stamp

    def _moved_at(self) -> float | None:
        with self._lock:
            return self._moved

    def _robot_accepted_after(self, t0: float) -> float | None:
        with self._lock:
            return min((stamp for stamp in self._robot_accepts if stamp >= t0), default=None)

    def navigate(self, pose: Pose2D) -> tuple[float, float, float]:
        """One goal to `pose` from standing still, waited for to succeed: ms to accepted, robot, motion."""
        self.odom.wait(lambda odom: base_speed(odom) < STILL, STILL_TIMEOUT, f"the {self.name} base standing still")
        goal_id = uuid.uuid4().hex
        with self._lock:
            self._moved = None
            t0 = self._t0 = time.time()
        try:
            handle = self.client.send(NavigateToPoseGoal(pose=pose), goal_id=goal_id, timeout=GOAL_TIMEOUT)
        except GoalRejected as exc:
            raise BenchError(
                f"{self.name}: the navigate goal to ({pose.x:.2f}, {pose.y:.2f}) was rejected: {exc}"
            ) from None
        except CallError as exc:
            raise BenchError(f"{self.name}: send_goal of the navigate goal failed: {exc}") from None
        accepted = time.time()
        wait_until(lambda: self._moved_at() is not None, MOVE_TIMEOUT, f"the {self.name} base moving")
        try:
            result = handle.result(RESULT_TIMEOUT)
        except CallError as exc:
            raise BenchError(f"{self.name}: no result of the navigate goal: {exc}") from None
        if result.state is not GoalState.SUCCEEDED:
            raise BenchError(f"{self.name}: the navigate goal ended {result.state}: {result.message}")
        wait_until(lambda: self._robot_accepted_after(t0) is not None, GOAL_TIMEOUT, f"the {self.name} robot's accept")
        robot, moved = self._robot_accepted_after(t0), self._moved_at()
        assert robot is not None and moved is not None
        return round((accepted - t0) * 1000, 3), round((robot - t0) * 1000, 3), round((moved - t0) * 1000, 3)

    def record(self, times: tuple[float, float, float]) -> None:
        for kept, ms in zip((self.accepted_ms, self.robot_ms, self.motion_ms), times, strict=True):
            kept.append(ms)


def native_path(stack: Stack) -> GoalPath:
    """The sim's acceptances: the ACCEPTED statuses of its action server on robot/navigate_to_pose."""
    path = GoalPath("native", stack.node)

    def on_status(status: GoalStatus) -> None:
        if status.state is GoalState.ACCEPTED:
            path.robot_accepted(status.stamp)

    stack.node.subscribe(keys.ROBOT_NAVIGATE.status, on_status)
    return path


def ros2_path(stack: Stack, ros: RosNode) -> GoalPath:
    """The stand-in's acceptances: each goal's GoalInfo stamp in its NavigateToPose GoalStatusArray."""
    path = GoalPath("ros2", stack.node)

    def on_status(message: Any) -> None:
        for status in message.status_list:
            path.robot_accepted(to_seconds(status.goal_info.stamp))

    status_topic = f"{Ros2Config().names.navigate_to_pose}/_action/status"
    ros.subscribe(status_topic, GOAL_STATUS_ARRAY_TYPE, on_status, qos=STATUS_QOS)
    return path


def navigate_rounds(path: GoalPath, rounds: int, warmup: int) -> None:
    """`warmup` goals not counted, then `rounds`: east and back in turn."""
    start = load_world().robot.start
    for i in range(warmup + rounds):
        pose = Pose2D(x=start.x + (LEG if i % 2 == 0 else 0.0), y=start.y, yaw=start.yaw)
        times = path.navigate(pose)
        if i >= warmup:
            path.record(times)
        which = f"warm-up goal {i + 1}/{warmup}" if i < warmup else f"goal {i - warmup + 1}/{rounds}"
        shown = " / ".join(f"{ms:.1f}" for ms in times)
        progress(f"{path.name} {which} to ({pose.x:.1f}, {pose.y:.1f}): ms to accepted / robot / moving {shown}")


# The cmd_vel stream


class TwistArrivals:
    """The stream's twists, told apart by angular_z, and when each came out on each path (wall time)."""

    def __init__(self) -> None:
        self.stamps: list[float] = []
        self.native: dict[int, float] = {}
        self.ros2: dict[int, float] = {}
        self.warm = threading.Event()  # a warm-up twist came out on the ROS 2 side
        self.seconds = 0.0
        self._index: dict[float, int] = {}
        self._decoder = runtime.decoder(Twist)

    def next_twist(self) -> Twist:
        i = len(self.stamps)
        turn = TURN + (i + 1) * STEP
        self._index[turn] = i
        stamp = time.time()
        self.stamps.append(stamp)
        return Twist(angular_z=turn, stamp=stamp)

    def on_native(self, _key: str, payload: bytes) -> None:
        now = time.time()
        self._arrived(self.native, self._decoder.decode(payload).angular_z, now)

    def on_ros2(self, message: Any) -> None:
        now = time.time()
        turn = float(message.angular.z)
        if turn == TURN:
            self.warm.set()
        self._arrived(self.ros2, turn, now)

    def _arrived(self, arrivals: dict[int, float], turn: float, now: float) -> None:
        i = self._index.get(turn)
        if i is not None:
            arrivals.setdefault(i, now)

    def latencies_ms(self, arrivals: dict[int, float]) -> list[float]:
        return [(at - self.stamps[i]) * 1000 for i, at in arrivals.items()]

    def hops_ms(self) -> list[float]:
        return [(at - self.native[i]) * 1000 for i, at in self.ros2.items() if i in self.native]

    def all_in(self) -> bool:
        return len(self.native) == len(self.ros2) == len(self.stamps)


def stream(stack: Stack, ros: RosNode, rate: float, seconds: float) -> tuple[TwistArrivals, Vetoes]:
    node = stack.node
    arrivals = TwistArrivals()
    vetoes = Vetoes(node)
    node.subscribe_raw(keys.ROBOT_CMD_VEL.key(node.robot), arrivals.on_native)
    ros.subscribe(Ros2Config().names.cmd_vel, TWIST, arrivals.on_ros2)
    # Until a twist comes out on the robot's side: the backend passes cmd_vel once it has released the robot.
    deadline = time.monotonic() + READY_TIMEOUT
    while not arrivals.warm.wait(1.0 / WARMUP_HZ):
        if time.monotonic() > deadline:
            raise BenchError(f"no cmd_vel came out on the robot's ROS 2 cmd_vel within {READY_TIMEOUT:g} s")
        node.publish(keys.CMD_VEL, Twist(angular_z=TURN, stamp=time.time()))
    publisher = node.publisher(keys.CMD_VEL)
    progress(f"streaming cmd_vel at {rate:g} Hz for {seconds:g} s")
    arrivals.seconds = paced(rate, seconds, lambda: publisher.put(arrivals.next_twist()))
    with contextlib.suppress(BenchError):
        wait_until(arrivals.all_in, DRAIN, "every twist on both paths", poll=0.01)
    return arrivals, vetoes


# The bench


def bench(rate: float, seconds: float, rounds: int, warmup: int) -> dict[str, Any]:
    ros2_settings, endpoint, listen, native_settings = stack_settings()
    ros2_config: dict[str, dict[str, Any]] = {"ros2": {"endpoint": endpoint, **ROS2}, "ros2sim": {"listen": endpoint}}
    with tempfile.TemporaryDirectory(prefix="bench-ros2-") as tmp:
        with (
            robot_stack(ROBOT_BACKENDS["ros2-standin"], ros2_settings, Path(tmp), ros2_config) as ros2_stack,
            robot_network(endpoint, listen) as ros,
        ):
            ros2 = ros2_path(ros2_stack, ros)
            navigate_rounds(ros2, rounds, warmup)
            arrivals, vetoes = stream(ros2_stack, ros, rate, seconds)
        with robot_stack(ROBOT_BACKENDS["sim"], native_settings, Path(tmp), {}) as native_stack:
            native = native_path(native_stack)
            navigate_rounds(native, rounds, warmup)
    return {**stream_summary(arrivals, vetoes), **goal_summary(ros2, native)}


def p50_p99(prefix: str, ms: list[float]) -> dict[str, float]:
    if not ms:
        return {}
    p50, p99 = ms_summary(ms)
    return {f"{prefix}_p50_ms": p50, f"{prefix}_p99_ms": p99}


def added(result: dict[str, Any], what: str, quantiles: tuple[str, ...] = ("p50", "p99")) -> dict[str, float]:
    """ros2 - native of `what`'s quantiles, where both were measured."""
    out = {}
    for q in quantiles:
        ros2, native = result.get(f"{what}ros2_{q}_ms"), result.get(f"{what}native_{q}_ms")
        if ros2 is not None and native is not None:
            out[f"{what}added_{q}_ms"] = round(ros2 - native, 4)
    return out


def stream_summary(arrivals: TwistArrivals, vetoes: Vetoes) -> dict[str, Any]:
    sent = len(arrivals.stamps)
    result: dict[str, Any] = {
        "rate_hz": round(sent / arrivals.seconds, 1),
        "duration_s": round(arrivals.seconds, 3),
        "sent": sent,
        "native_received": len(arrivals.native),
        "ros2_received": len(arrivals.ros2),
        "native_lost": sent - len(arrivals.native),
        "ros2_lost": sent - len(arrivals.ros2),
        "vetoed": vetoes.count,
        **p50_p99("native", arrivals.latencies_ms(arrivals.native)),
        **p50_p99("ros2", arrivals.latencies_ms(arrivals.ros2)),
        **p50_p99("hop", arrivals.hops_ms()),
        "errors": [f"{vetoes.count} twists vetoed by safety, the first: {vetoes.first}"] if vetoes.count else [],
    }
    result |= added(result, "")
    if not arrivals.ros2:
        result["errors"].append("no twist sent came out on the robot's ROS 2 cmd_vel")
    return result


def goal_summary(ros2: GoalPath, native: GoalPath) -> dict[str, Any]:
    result: dict[str, Any] = {"goal_trials": min(len(ros2.motion_ms), len(native.motion_ms))}
    for path in (native, ros2):
        result |= p50_p99(f"goal_accepted_{path.name}", path.accepted_ms)
        result |= p50_p99(f"goal_robot_{path.name}", path.robot_ms)
        result |= p50_p99(f"goal_motion_{path.name}", path.motion_ms)
    for what in ("goal_accepted_", "goal_robot_", "goal_motion_"):
        result |= added(result, what, ("p50",))
    result["goal_ms"] = {
        path.name: {"accepted": path.accepted_ms, "robot": path.robot_ms, "motion": path.motion_ms}
        for path in (native, ros2)
    }
    return result


def goals_met(result: dict[str, Any]) -> dict[str, bool]:
    goal = GOALS["goal_added_p50_ms"]
    met = {"nothing_lost": result.get("native_lost") == 0 and result.get("ros2_lost") == 0}
    for key in ("added_p50_ms", "goal_robot_added_p50_ms"):
        if result.get(key) is not None:
            met[key] = result[key] <= goal
    return met


def run(args: argparse.Namespace) -> dict[str, Any]:
    defaults: dict[str, Any] = {
        "rate_hz": None,
        "sent": 0,
        "native_lost": None,
        "ros2_lost": None,
        "native_p50_ms": None,
        "native_p99_ms": None,
        "ros2_p50_ms": None,
        "ros2_p99_ms": None,
        "added_p50_ms": None,
        "added_p99_ms": None,
        "goal_trials": 0,
        **GOALS,
    }
    result = measured(defaults, lambda: bench(args.rate, args.seconds, args.trials, args.warmup), progress)
    result["goals_met"] = goals_met(result)
    result["notes"] = notes(
        requested_rate_hz=args.rate,
        goal_warmup_rounds=args.warmup,
        native="twists on cmd/cmd_vel, checked by safety, arriving on robot/cmd_vel",
        ros2="the same twists as geometry_msgs/msg/Twist on the robot's ROS 2 cmd_vel (rmw_zenoh keys), "
        "sent on by the ros2 backend",
        added="ros2 - native, of the p50s and of the p99s; hop: ros2 arrival - native arrival of each twist",
        goal=f"navigate_to_pose {LEG:g} m east of the start pose and back, through safety, on the ros2 stack "
        "then on the native one; ms from send_goal to: accepted (the reply here), robot (the robot's action "
        "server accepting, by its stamp), motion (the first odometry sample above 0.01 m/s or rad/s, by its stamp)",
        sim=SIM,
        ros2_config=ROS2,
    )
    return result


def print_table(result: dict[str, Any]) -> None:
    def pair(a: str, b: str) -> str:
        return f"{show(result.get(a))} / {show(result.get(b))}"

    goal = f"p50 <= {show(GOALS['goal_added_p50_ms'])}"
    rows = [
        ("cmd_vel send rate Hz", show(result.get("rate_hz")), ""),
        ("sent / lost native / lost ros2", f"{result['sent']} / {pair('native_lost', 'ros2_lost')}", "0 lost"),
        ("cmd_vel native p50 / p99 ms (baseline)", pair("native_p50_ms", "native_p99_ms"), ""),
        ("cmd_vel ros2 p50 / p99 ms", pair("ros2_p50_ms", "ros2_p99_ms"), ""),
        ("cmd_vel added p50 / p99 ms", pair("added_p50_ms", "added_p99_ms"), goal),
        ("backend hop p50 / p99 ms", pair("hop_p50_ms", "hop_p99_ms"), ""),
        ("goal accepted p50 ms native / ros2", pair("goal_accepted_native_p50_ms", "goal_accepted_ros2_p50_ms"), ""),
        ("goal at the robot p50 ms native / ros2", pair("goal_robot_native_p50_ms", "goal_robot_ros2_p50_ms"), ""),
        ("goal moving p50 ms native / ros2", pair("goal_motion_native_p50_ms", "goal_motion_ros2_p50_ms"), ""),
        ("goal added p50 ms: accepted", show(result.get("goal_accepted_added_p50_ms")), ""),
        ("goal added p50 ms: at the robot", show(result.get("goal_robot_added_p50_ms")), goal),
        ("goal added p50 ms: moving", show(result.get("goal_motion_added_p50_ms")), ""),
    ]
    title = (
        f"ROS 2 backend vs native sim ({show(result.get('duration_s'))} s of cmd_vel, {result['goal_trials']} goals)"
    )
    print_rows(title, rows, result["errors"])
    if result.get("goal_ms"):
        for name, times in result["goal_ms"].items():
            print(f"{name} goal at the robot ms: {statistics.median(times['robot']):.2f} median of {times['robot']}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--rate",
        type=bounded(float, 1.0, 1200.0),
        default=1000.0,
        help="twists per second (safety passes 1200 at most)",
    )
    parser.add_argument(
        "--seconds", type=bounded(float, 0.0, 60.0, open_low=True), default=10.0, help="seconds of cmd_vel"
    )
    parser.add_argument("--trials", type=bounded(int, 1, 200), default=20, help="navigate goals to each stack")
    parser.add_argument(
        "--warmup", type=bounded(int, 0, 20), default=2, help="navigate goals to each stack first, not counted"
    )


def main(argv: list[str] | None = None) -> None:
    bench_main(PROG, __doc__ or "", add_arguments, run, print_table, argv)


if __name__ == "__main__":
    main()
