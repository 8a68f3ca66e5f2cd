"""Real processes over real Zenoh on loopback: a stack per test, always torn down."""

from __future__ import annotations

import subprocess
import sys
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from schemas import keys
from schemas.robot import Odometry
from services.runtime import ALL_SERVICES, SERVICES, Node, NodeSettings
from tests.fastsim import FAST_SIM
from tests.sessions import LOADED_HEARTBEAT_MAX_AGE, LOADED_HEARTBEAT_TIMEOUT, free_ports
from tether.supervisor import Supervisor

STARTUP_TIMEOUT = 90.0
ODOMETRY_SAMPLES = 3


@dataclass
class Stack:
    settings: NodeSettings
    supervisor: Supervisor
    node: Node
    tmp: Path
    token_file: Path

    @property
    def recordings(self) -> Path:
        return self.tmp / "recordings"


# The heartbeat's bounds for a loaded machine (tests/sessions.py), as [sim] lines, in stacks whose tests
# are not about them. The bounds themselves are tested at their defaults by the tests marked realtime,
# which run at normal priority and pass strict_timing=True (and by tests/robot_contract, test_multihost,
# test_ros2sim).
LOADED_MACHINE_HEARTBEAT = (
    f"heartbeat_timeout = {LOADED_HEARTBEAT_TIMEOUT}\nheartbeat_max_age = {LOADED_HEARTBEAT_MAX_AGE}\n"
)


def write_config(
    path: Path,
    realtime_factor: float,
    policy: Path | None = None,
    extra: str = "",
    strict_timing: bool = False,
    sim_options: str = "",
    safety_options: str = "",
) -> Path:
    """The stack's config file; `extra`: more tables, appended; `strict_timing`: the robot's
    heartbeat bounds at their defaults (else LOADED_MACHINE_HEARTBEAT); `sim_options`, `safety_options`:
    more lines of the [sim] and [safety] tables."""
    path.write_text(
        f"[sim]\nrealtime_factor = {realtime_factor}\n"
        + ("" if strict_timing else LOADED_MACHINE_HEARTBEAT)
        + sim_options
        + "\n"
        f'[recorder]\noutput_dir = "{path.parent / "recordings"}"\n\n'
        f'[safety]\noperator_token_file = "{path.parent / "operator-token"}"\n'
        + (f'policy = "{policy}"\n' if policy else "")
        + safety_options
        + (f"\n{extra}" if extra else "")
    )
    return path


# What a test stack runs unless it asks for more: every service but the planner, which has no LLM
# endpoint to talk to here (tests/integration/test_agents.py starts it with a scripted one).
STACK_SERVICES = tuple(s for s in SERVICES if s != "planner")


def start_stack(
    tmp: Path,
    realtime_factor: float,
    services: tuple[str, ...] = STACK_SERVICES,
    policy: Path | None = None,
    extra_config: str = "",
    strict_timing: bool = False,
    sim_options: str = "",
    safety_options: str = "",
) -> Stack:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))
    config = write_config(
        tmp / "tether.toml", realtime_factor, policy, extra_config, strict_timing, sim_options, safety_options
    )
    token = tmp / "operator-token"
    supervisor = Supervisor(settings, tmp / "logs", config, extra_env={"TETHER_OPERATOR_TOKEN_FILE": str(token)})
    node: Node | None = None
    try:
        supervisor.start_all(services)
        node = Node("cli", settings)
        missing = node.wait_alive(services, STARTUP_TIMEOUT)
        assert not missing, f"services not up: {missing}\n" + "\n".join(supervisor.log_tail(s) for s in missing)
        if "sim" in services:
            # Alive is not yet reporting: until safety has heard the robot's odometry, a plan is vetoed
            # for an unknown pose. A few samples here have reached safety's subscriber too.
            assert wait_for_odometry(node, ODOMETRY_SAMPLES, STARTUP_TIMEOUT), "the sim is up but sends no odometry"
    except BaseException:
        if node is not None:
            node.close()
        supervisor.stop_all()
        dump_logs(supervisor, services)
        raise
    return Stack(settings, supervisor, node, tmp, token)


def wait_for_odometry(node: Node, samples: int, timeout: float) -> bool:
    """True once `samples` odometry messages have arrived, False after `timeout` seconds."""
    heard: list[Odometry] = []
    enough = threading.Event()

    def on_odom(msg: Odometry) -> None:
        heard.append(msg)
        if len(heard) >= samples:
            enough.set()

    subscription = node.subscribe(keys.ODOM, on_odom)
    try:
        return enough.wait(timeout)
    finally:
        subscription.undeclare()


def stop_stack(stack: Stack) -> None:
    stack.node.close()
    stack.supervisor.stop_all()
    dump_logs(stack.supervisor, tuple(stack.supervisor.procs))


def tether_cli(stack: Stack, *args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    """The `tether` command line against this stack's services, as a user runs it."""
    return run_tether(stack.supervisor, *args, stdin=stdin)


def run_tether(supervisor: Supervisor, *args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    """The `tether` command line with the robot name and ports of `supervisor`'s services.

    In a session of its own, as from an operator's terminal, and so (autogroup scheduling) in a
    scheduling group of its own, as each service is (tether.supervisor). In the pytest worker's, at
    `make test`'s low priority beside its busy workers (tests/suite.py), a command shared their CPU,
    and `tether world move` once found no simulator alive within its 2 s."""
    return subprocess.run(
        [sys.executable, "-m", "tether", *args],
        env=supervisor.env(),
        input=stdin,
        capture_output=True,
        text=True,
        timeout=120,
        start_new_session=True,
    )


def dump_logs(supervisor: Supervisor, services: tuple[str, ...]) -> None:
    """Shown by pytest only when the test failed."""
    for service in services:
        print(f"----- {service} log -----\n{supervisor.log_tail(service, 60)}")


# For tests that judge where things end up, not how or when: the sim up to twenty times faster than
# real time (the most `[sim] realtime_factor` allows; as fast as the machine lets it), its physics at
# 120 Hz (half the default: half the CPU per sim second; tests/fastsim.py).
# Profiled (py-spy) on the tours: pybullet's step was about two thirds of the sim's CPU, so 120 Hz at
# 20x costs what 240 Hz at 10x did.
FAST = 20.0


@pytest.fixture
def stack(tmp_path: Path) -> Iterator[Stack]:
    """Every service, the sim fast (FAST, FAST_SIM)."""
    s = start_stack(tmp_path, realtime_factor=FAST, sim_options=FAST_SIM)
    try:
        yield s
    finally:
        stop_stack(s)


@pytest.fixture
def realtime_stack(tmp_path: Path) -> Iterator[Stack]:
    """Every service with the sim at real time, for measuring stops in sim time finely."""
    s = start_stack(tmp_path, realtime_factor=1.0, strict_timing=True)
    try:
        yield s
    finally:
        stop_stack(s)
