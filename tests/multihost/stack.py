"""A TLS deployment of tether across hosts in namespaces: the router and the planner side on the edge, each
robot's sim, safety and recorder on its own host, the CLI on an operator host; watched from here.

Robot r1's host reaches the router through a link proxy on its own side of the link (the proxy holds
169.254.0.1 on the robot host's loopback and passes everything on to the edge over the veth), so a
test can delay, stall or reset its traffic; its veth can be taken down and narrowed as well. Robot
r2's host is connected directly.

This process (the root namespace, outside the topology) watches each robot with that robot's
operator identity through a second proxy, the tap: it listens on 127.0.0.1 here and opens its
connections in the edge's namespace, straight to the router, so the watch never crosses a link a
test breaks. The router's certificate names localhost, so TLS holds on the tap as on every link.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from schemas import keys
from schemas.executor import ExecutePlanGoal
from schemas.robot import Odometry
from schemas.safety import SafetyStatus
from schemas.world import Empty, GroundTruth
from services.runtime import Node, NodeSettings
from tests.logs import print_tails
from tests.multihost.linkproxy import ProxyControl
from tests.multihost.netns import ROUTER_ALT_IP, ROUTER_IP, ROUTER_PORT, Proc, Topology, sh
from tests.sessions import free_port
from tether.client import PlanRun, PlanSender

ROBOT_SERVICES = ("sim", "safety", "recorder")
EDGE_SERVICES = ("parser", "resolver", "executor", "planner")
STARTUP_TIMEOUT = 90.0
# Below these the base counts as still, above MOVING as moving (m/s or rad/s), as in bench.service.
STILL = 0.01
MOVING = 0.1


@dataclass
class Sample:
    stamp: float  # the sim's wall clock
    arrived: float
    speed: float


@dataclass
class Beat:
    arrived: float
    stamp: float
    latched: bool


@dataclass
class Watch:
    """Everything this process hears of one robot, through the tap: odometry and safety's heartbeat."""

    node: Node
    odom: list[Sample] = field(default_factory=list)
    beats: list[Beat] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def start(self) -> None:
        self.node.subscribe(keys.ODOM, self._on_odom)
        self.node.subscribe(keys.HEARTBEAT, self._on_beat)

    def _on_odom(self, odom: Odometry) -> None:
        with self.lock:
            self.odom.append(Sample(odom.stamp, time.time(), max(abs(odom.linear_x), abs(odom.angular_z))))

    def _on_beat(self, beat: SafetyStatus) -> None:
        with self.lock:
            self.beats.append(Beat(time.time(), beat.stamp, beat.estop.latched))

    def samples(self, since: float = 0.0, until: float = float("inf")) -> list[Sample]:
        """Odometry stamped in [since, until], in stamp order."""
        with self.lock:
            return sorted((s for s in self.odom if since <= s.stamp <= until), key=lambda s: s.stamp)

    def moving(self) -> bool:
        with self.lock:
            return bool(self.odom) and self.odom[-1].speed > MOVING

    def halt_after(self, t0: float, until: float = float("inf")) -> float | None:
        """Seconds from `t0` to the first sample stamped after it from which on every sample up to `until` is still."""
        halt = None
        for sample in self.samples(t0, until):
            if sample.speed >= STILL:
                halt = None
            elif halt is None:
                halt = sample.stamp
        return None if halt is None else halt - t0

    def clear_after(self, after: float) -> bool:
        with self.lock:
            return any(b.arrived > after and not b.latched for b in self.beats)

    def fresh_beat(self, after: float) -> bool:
        with self.lock:
            return any(b.arrived > after for b in self.beats)

    def steady(self, since: float, gap: float) -> bool:
        """Odometry and heartbeats arrived from `since` until now (Unix seconds) never more than `gap` apart:
        neither the robot's stack nor the link held them up."""
        now = time.time()
        with self.lock:
            streams = ([s.arrived for s in self.odom], [b.arrived for b in self.beats])
        for arrivals in streams:
            times = [since, *(t for t in arrivals if t > since), now]
            if any(b - a > gap for a, b in itertools.pairwise(times)):
                return False
        return True


@dataclass
class Robot:
    name: str
    host: str  # the topology's role of its host
    link: ProxyControl | None  # its host's link proxy, if it has one
    on_robot: Proc | None = None  # `tether up --only sim,safety,recorder` there
    on_edge: Proc | None = None  # `tether up --only parser,resolver,executor` on the edge
    watch: Watch | None = None
    sender: PlanSender | None = None

    @property
    def node(self) -> Node:
        assert self.watch is not None
        return self.watch.node


def clean_env() -> dict[str, str]:
    """This environment without any TETHER_* setting: a deployment's process takes its own from its flags."""
    return {k: v for k, v in os.environ.items() if not k.startswith("TETHER_")}


def tether_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "tether", *args]


def read_json5(path: Path) -> dict[str, Any]:
    """A config `tether deploy init` wrote: JSON after `//` comment lines."""
    text = "\n".join(line for line in path.read_text().splitlines() if not line.lstrip().startswith("//"))
    value: dict[str, Any] = json.loads(text)
    return value


def set_sim_options(toml: Path, options: dict[str, float]) -> None:
    """Add `options` to the [sim] table of a robot's tether.toml (made if missing)."""
    lines = "".join(f"{k} = {v}\n" for k, v in options.items())
    text = toml.read_text()
    if re.search(r"^\[sim\]\s*$", text, flags=re.M):
        text = re.sub(r"^\[sim\]\s*$\n?", lambda m: "[sim]\n" + lines, text, count=1, flags=re.M)
    else:
        text += f"\n[sim]\n{lines}"
    toml.write_text(text)


class MultiHost:
    """The deployment running across the topology. close() stops and removes everything."""

    def __init__(self, workdir: Path, robots: Sequence[tuple[str, str]], sim: dict[str, float]) -> None:
        self.workdir = workdir
        self.deploy = workdir / "deploy"
        roles = [host for _, host in robots]
        self.topo = Topology([*roles, "operator"], workdir)
        self.robots: dict[str, Robot] = {}
        self.router: Proc | None = None
        try:
            self._start(robots, sim)
        except BaseException:
            self.print_logs()
            self.close()
            raise

    def _start(self, robots: Sequence[tuple[str, str]], sim: dict[str, float]) -> None:
        init = ["deploy", "init", str(self.deploy), "--tls", "--router", ROUTER_IP]
        for name, _ in robots:
            init += ["--robot", name]
        self.run_root(*init)
        for name, _ in robots:
            set_sim_options(self.deploy / name / "tether.toml", sim)
        self.start_router()
        for i, (name, host) in enumerate(robots):
            link = None
            if i == 0:
                # The first robot's host reaches the router through its link proxy (see the docstring).
                sh("ip", "-n", self.topo.host(host).netns, "addr", "add", f"{ROUTER_IP}/32", "dev", "lo")
                link = self.topo.start_proxy(host, f"{ROUTER_IP}:{ROUTER_PORT}", f"{ROUTER_ALT_IP}:{ROUTER_PORT}")
            self.robots[name] = robot = Robot(name, host, link)
            robot.on_robot = self.up(name, host, ROBOT_SERVICES)
            robot.on_edge = self.up(name, "edge", EDGE_SERVICES)
        tap_port = free_port()
        self.topo.start_proxy(
            "root", f"127.0.0.1:{tap_port}", f"{ROUTER_IP}:{ROUTER_PORT}", connect_netns=self.topo.edge.netns
        )
        for name, robot in self.robots.items():
            conf = read_json5(self.deploy / name / "operator.json5")
            conf["connect"]["endpoints"] = [f"tls/localhost:{tap_port}"]
            tap = self.deploy / name / "tap-operator.json5"
            tap.write_text(json.dumps(conf, indent=2))
            tap.chmod(0o600)
            robot.watch = Watch(open_node(NodeSettings(robot=name, zenoh_config=tap), STARTUP_TIMEOUT))
            robot.watch.start()
            robot.sender = PlanSender(robot.node)
        for name in self.robots:
            missing = self.wait_alive(name, STARTUP_TIMEOUT)
            assert not missing, f"robot {name}: services not up within {STARTUP_TIMEOUT:g} s: {sorted(missing)}"
            # A new deployment's safety starts latched (no latch file yet): the operator resets it.
            self.reset(name)

    def reset(self, robot: str) -> None:
        """The operator's reset from the operator host, then a heartbeat with the e-stop clear heard here."""
        asked = time.time()
        done = self.cli(robot, "operator", "reset", "--token-file", str(self.deploy / robot / "operator.token"))
        assert done.returncode == 0, f"reset of {robot}: exit {done.returncode}: {done.stdout}{done.stderr}"
        watch = self.robots[robot].watch
        assert watch is not None
        wait_for(lambda: watch.clear_after(asked), 10.0, f"a heartbeat of {robot} with the e-stop clear")

    # Processes

    def run_root(self, *args: str) -> str:
        import subprocess

        done = subprocess.run(tether_argv(*args), env=clean_env(), capture_output=True, text=True, timeout=120)
        if done.returncode != 0:
            raise RuntimeError(f"tether {' '.join(args)}: exit {done.returncode}\n{done.stdout}\n{done.stderr}")
        return done.stdout

    def start_router(self) -> Proc:
        self.router = self.topo.spawn("edge", "router", tether_argv("router", str(self.deploy)), env=clean_env())
        return self.router

    def up(self, robot: str, host: str, services: Sequence[str]) -> Proc:
        log_dir = self.workdir / "logs" / f"{robot}-{host}"
        argv = tether_argv("up", "--deploy", str(self.deploy), "--robot", robot, "--only", ",".join(services))
        return self.topo.spawn(host, f"up-{robot}-{host}", [*argv, "--log-dir", str(log_dir)], env=clean_env())

    def service_pid(self, robot: str, service: str) -> int:
        """The pid of `service` of `robot`, a child of one of its `tether up` processes."""
        r = self.robots[robot]
        parents = {p.popen.pid for p in (r.on_robot, r.on_edge) if p is not None}
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                stat = (entry / "stat").read_text()
                argv = (entry / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid in parents and b"run" in argv and service.encode() in argv:
                return int(entry.name)
        raise LookupError(f"no running {service} of robot {robot}")

    def cli(self, robot: str, identity: str, *args: str, stdin: str | None = None, timeout: float = 60.0) -> Any:
        """`tether --zenoh-config DIR/<robot>/<identity>.json5 --robot ROBOT ARGS` on the operator host."""
        import subprocess

        conf = self.deploy / robot / f"{identity}.json5"
        argv = ["ip", "netns", "exec", self.topo.host("operator").netns]
        argv += tether_argv("--zenoh-config", str(conf), "--robot", robot, *args)
        return subprocess.run(argv, env=clean_env(), input=stdin, capture_output=True, text=True, timeout=timeout)

    # Watching

    def wait_alive(
        self, robot: str, timeout: float, services: Sequence[str] = (*ROBOT_SERVICES, *EDGE_SERVICES)
    ) -> set[str]:
        return self.robots[robot].node.wait_alive(services, timeout)

    def truth(self, robot: str) -> GroundTruth:
        return self.robots[robot].node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)

    def send(self, robot: str, plan: str) -> Any:
        sender = self.robots[robot].sender
        assert sender is not None
        return sender.send(ExecutePlanGoal(text=plan))

    def result(self, robot: str, handle: Any, timeout: float) -> PlanRun:
        sender = self.robots[robot].sender
        assert sender is not None
        return sender.wait(handle, timeout)

    def print_logs(self, lines: int = 40) -> None:
        """Every log's tail: pytest shows them when a test failed."""
        print_tails(self.workdir / "logs", lines)

    def close(self) -> None:
        for robot in self.robots.values():
            if robot.watch is not None:
                with contextlib.suppress(Exception):
                    robot.watch.node.close()
        self.topo.close()


def open_node(settings: NodeSettings, timeout: float) -> Node:
    """A session of this process, tried again until the router answers (it may still be starting)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return Node("cli", settings)
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def wait_for(condition: Any, timeout: float, what: str, poll: float = 0.02) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout:g} s")
        time.sleep(poll)


@contextlib.contextmanager
def multihost(workdir: Path, robots: Sequence[tuple[str, str]], sim: dict[str, float]) -> Iterator[MultiHost]:
    stack = MultiHost(workdir, robots, sim)
    try:
        yield stack
    finally:
        stack.close()
