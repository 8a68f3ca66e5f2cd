"""The robot backends the contract suite runs against, each as a real process, with the test in safety's place."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from schemas import keys
from schemas.actions import CANCEL_ALL, CancelGoal
from schemas.robot import JointState, Odometry
from schemas.world import PerceivedHumans, PerceivedObjects
from services.errors import CallError
from services.robotlink import Signer
from services.runtime import ALL_SERVICES, Node, NodeSettings
from services.sim.config import SimConfig
from tests.robot_contract.played_safety import PlayedSafety
from tests.sessions import free_ports
from tests.watch import Watch
from tether.supervisor import Supervisor

STARTUP_TIMEOUT = 90.0


@dataclass(frozen=True)
class Lane:
    """A straight stretch of the backend's world clear of walls and furniture, from where the robot
    starts (or first stands when the suite begins), for the suite's goals to drive along."""

    x: float  # where it begins (map frame, metres)
    y: float
    heading: float  # its direction (radians)
    length: float  # metres

    def along(self, x: float, y: float) -> float:
        """How far along the lane the point (x, y) is."""
        return (x - self.x) * math.cos(self.heading) + (y - self.y) * math.sin(self.heading)

    def point(self, s: float) -> tuple[float, float]:
        """The point `s` metres along the lane."""
        return self.x + s * math.cos(self.heading), self.y + s * math.sin(self.heading)


@dataclass(frozen=True)
class Backend:
    """How to start one robot backend and the timing it was configured with, which the suite checks.

    Adding a backend to the suite is adding one entry to BACKENDS.
    """

    name: str  # the test id
    service: str  # what `tether run` starts; also its liveliness token
    config: str  # its config file (TOML)
    heartbeat_timeout: float  # wall seconds without safety's heartbeat before the robot stops
    first_heartbeat_wait: float  # how long a goal before the first heartbeat waits for one
    cmd_vel_timeout: float  # wall seconds a cmd_vel holds without a newer one
    odom_hz: float
    joint_states_hz: float
    objects_hz: float
    humans_hz: float
    lane: Lane
    robot: str | None = None  # the robot's name; None: a fresh one per run, so runs never share keys
    # Started first and stopped last: the robot a backend drives, when it is a process of its own.
    robot_service: str | None = None
    # `config` may name {endpoint}: a free loopback Zenoh endpoint for the robot's own network.


def sim_backend(config: SimConfig) -> Backend:
    toml = (
        f"[sim]\nrealtime_factor = {config.realtime_factor}\nheartbeat_timeout = {config.heartbeat_timeout}\n"
        f"first_heartbeat_wait = {config.first_heartbeat_wait}\n"
        f"cmd_vel_timeout = {config.cmd_vel_timeout}\nodom_hz = {config.odom_hz}\n"
        f"joint_states_hz = {config.joint_states_hz}\nobjects_hz = {config.objects_hz}\n"
        f"humans_hz = {config.humans_hz}\n"
    )
    return Backend(
        name="sim",
        service="sim",
        config=toml,
        heartbeat_timeout=config.heartbeat_timeout,
        first_heartbeat_wait=config.first_heartbeat_wait,
        cmd_vel_timeout=config.cmd_vel_timeout,
        odom_hz=config.odom_hz,
        joint_states_hz=config.joint_states_hz,
        objects_hz=config.objects_hz,
        humans_hz=config.humans_hz,
        # The household's corridor from the start pose (6.0, 1.2) east.
        lane=Lane(x=6.0, y=1.2, heading=0.0, length=4.0),
    )


def ros2_backend(config: SimConfig) -> Backend:
    """The ros2 backend driving the stand-in robot (the sim behind a ROS 2 face) over rmw_zenoh keys."""
    sim = sim_backend(config)
    toml = (
        f'{sim.config}\n[ros2]\nendpoint = "{{endpoint}}"\nheartbeat_timeout = {config.heartbeat_timeout}\n'
        f"first_heartbeat_wait = {config.first_heartbeat_wait}\nodom_hz = {config.odom_hz}\n"
        f"joint_states_hz = {config.joint_states_hz}\nobjects_hz = {config.objects_hz}\n"
        f"humans_hz = {config.humans_hz}\n\n"
        f'[ros2sim]\nlisten = "{{endpoint}}"\ncmd_vel_timeout = {config.cmd_vel_timeout}\n'
    )
    return dataclasses.replace(sim, name="ros2", service="ros2", config=toml, robot_service="ros2sim")


# The sim at real time: faster, on two loaded cores it falls behind the wall clock and its reports
# sag below their rates; the suite's goals are short, so it is no slower for it.
# A goal before the first heartbeat waits 1 s for it rather than the default 3 s: the same path, sooner.
CONTRACT_SIM = SimConfig(realtime_factor=1.0, first_heartbeat_wait=1.0)
BACKENDS = [sim_backend(CONTRACT_SIM), ros2_backend(CONTRACT_SIM)]


# What a robot reports, each at the rate its Backend gives (`odom_hz`, ...), each watched by a RunningBackend.
REPORTS = ("odom", "joint_states", "objects", "humans")


@dataclass
class RunningBackend:
    """One running backend, the test's node next to it, and what the robot has reported so far."""

    backend: Backend
    settings: NodeSettings
    supervisor: Supervisor
    node: Node
    safety: PlayedSafety
    odom: Watch[Odometry]
    joint_states: Watch[JointState]
    objects: Watch[PerceivedObjects]
    humans: Watch[PerceivedHumans]
    # Where each report's rate is measured from (an index into its Watch), set for all at once.
    rate_starts: dict[str, int] = dataclasses.field(default_factory=dict)

    def rate_start(self, topic: str) -> int:
        """Where `topic`'s rate is measured from: for all four reports the moment the first test of
        their rates asked, so that their windows run side by side and not one after another (about
        4 s less per backend in `make test`'s part that runs alone)."""
        if not self.rate_starts:
            self.rate_starts.update({name: len(getattr(self, name)) for name in REPORTS})
        return self.rate_starts[topic]

    def cancel_everything(self) -> None:
        for action in (keys.ROBOT_NAVIGATE, keys.ROBOT_TRAJECTORY, keys.ROBOT_GRIPPER):
            # No answer in time is no reason to fail a test that passed: the next goal preempts anyway.
            with contextlib.suppress(CallError):
                self.node.call(action.cancel_goal, CancelGoal(goal_id=CANCEL_ALL), timeout=5.0)


@contextlib.contextmanager
def running(backend: Backend, tmp: Path, *, beating: bool) -> Iterator[RunningBackend]:
    """`backend` as a real process next to the test's node, always stopped, also on failure; the
    played safety's heartbeat from the start when `beating`."""
    robot = backend.robot or f"t{uuid.uuid4().hex[:8]}"
    settings = NodeSettings(robot=robot, base_port=free_ports(len(ALL_SERVICES)))
    config = tmp / "tether.toml"
    config.write_text(backend.config.replace("{endpoint}", f"tcp/127.0.0.1:{free_ports()}"))
    supervisor = Supervisor(settings, tmp / "logs", config)
    node: Node | None = None
    safety: PlayedSafety | None = None
    services = [s for s in (backend.robot_service, backend.service) if s is not None]
    try:
        for service in services:
            supervisor.start(service)
        node = Node("cli", settings)
        # The test plays safety: it signs what it sends to the robot with the stack's robot key.
        node.signer = Signer(supervisor.robot_key())
        odom, joint_states = Watch(node, keys.ODOM), Watch(node, keys.JOINT_STATES)
        objects, humans = Watch(node, keys.OBJECTS), Watch(node, keys.HUMANS)
        missing = node.wait_alive(services, STARTUP_TIMEOUT)
        assert not missing, "\n".join(f"{s} not up:\n{supervisor.log_tail(s)}" for s in sorted(missing))
        safety = PlayedSafety(settings, supervisor.robot_key_file, beating=beating)
        yield RunningBackend(backend, settings, supervisor, node, safety, odom, joint_states, objects, humans)
    finally:
        if safety is not None:
            safety.close()
        if node is not None:
            node.close()
        supervisor.stop_all()
        # Shown by pytest only when a test failed.
        for service in services:
            print(f"----- {service} log -----\n{supervisor.log_tail(service, 60)}")


@pytest.fixture(scope="module", params=BACKENDS, ids=lambda b: b.name)
def backend_process(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[RunningBackend]:
    """The backend started once for the module's tests."""
    backend: Backend = request.param
    with running(backend, tmp_path_factory.mktemp(f"robot-{backend.name}"), beating=True) as started:
        yield started


@pytest.fixture(params=BACKENDS, ids=lambda b: b.name)
def unheard_robot(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[RunningBackend]:
    """A backend of its own that has not yet heard a heartbeat (safety not started)."""
    with running(request.param, tmp_path, beating=False) as started:
        yield started


@pytest.fixture
def robot(backend_process: RunningBackend) -> Iterator[RunningBackend]:
    """The module's backend, with safety's heartbeat present and clear, and no goal running."""
    backend_process.safety.set()
    assert backend_process.safety.beats(3), "the played safety's heartbeat thread stopped"
    yield backend_process
    backend_process.safety.set()
    backend_process.cancel_everything()
