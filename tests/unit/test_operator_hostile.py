"""What others wrote, as the operator's commands print it: a plan asked for approval by any peer, and
safety's replies quoting it, reach the terminal with their control characters escaped. Safety is the
real node on a real Zenoh session; the CLI runs in this process on another."""

from __future__ import annotations

import os
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import msgspec
import pytest
from typer.testing import CliRunner

from schemas import keys
from schemas.common import Pose2D
from schemas.plan import GroundedPlan, NavigateStep, Plan, Step
from schemas.robot import Odometry
from schemas.safety import ApprovalRequest, ApprovalState, ControlMode, EstopState, ModeRequest
from services.robotmodel import ArmModel
from services.runtime import ALL_SERVICES, Node, NodeSettings
from services.safety.config import SafetyConfig
from services.safety.latch import EstopLatch
from services.safety.node import SafetyNode
from services.safety.policy import SafetyPolicy
from services.safety.policyfile import load_policy
from services.worldmodel import WorldModel, load_world
from tests.sessions import free_ports
from tether import cli

WAIT = 5.0
TOKEN = "token"
# Moves the cursor up, clears the line, writes a false verdict in green, retitles the terminal.
FAKE_VERDICT = "\x1b[2K\x1b[1A\x1b[32m(approved by safety)\x1b[0m"
RETITLE = "\x1b]0;pwned\x07"


def controls(text: str) -> list[str]:
    return [c for c in text if (ord(c) < 0x20 and c != "\n") or 0x7F <= ord(c) < 0xA0]


@dataclass
class Safety:
    settings: NodeSettings
    node: SafetyNode
    peer: Node
    token_file: Path

    def cli(self, *args: str) -> str:
        base = ["--robot", self.settings.robot, "--base-port", str(self.settings.base_port)]
        result = CliRunner().invoke(cli.app, [*base, *args])
        return result.stdout + result.stderr


@pytest.fixture
def safety(tmp_path: Path) -> Iterator[Safety]:
    world = load_world()
    arm = ArmModel(world.robot.arm_urdf)
    policy = SafetyPolicy(WorldModel(world), load_policy(None, world.robot, arm, world.keep_out), arm)
    (tmp_path / "estop.json").write_bytes(msgspec.json.encode(EstopState(latched=False)))
    token_file = tmp_path / "operator.token"
    token_file.write_text(TOKEN)
    os.chmod(token_file, 0o600)
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_ports(len(ALL_SERVICES)))
    with Node("safety", settings) as session:
        node = SafetyNode(session, policy, EstopLatch(TOKEN, tmp_path / "estop.json"), SafetyConfig())
        session.declare_alive()
        try:
            with Node("executor", settings) as peer:
                peer.declare_alive()
                assert not peer.wait_alive({"safety"}, WAIT), "the two sessions did not find each other"
                mode = ModeRequest(operator="alice", token=TOKEN, mode=ControlMode.SUPERVISED)
                assert peer.call(keys.SET_MODE, mode, timeout=WAIT).ok
                peer.publish(
                    keys.ODOM, Odometry(stamp=0.0, sim_time=0.0, pose=Pose2D(x=6.0, y=1.2), linear_x=0.0, angular_z=0.0)
                )
                deadline = time.monotonic() + WAIT
                while node.gate.pose() is None:
                    assert time.monotonic() < deadline, "safety never heard the odometry"
                    time.sleep(0.005)
                yield Safety(settings, node, peer, token_file)
        finally:
            node.close()


def ask(safety: Safety, goal_id: str) -> None:
    """A plan asked for approval as any peer may ask: its label and target hold terminal controls."""
    plan = GroundedPlan(
        steps=[NavigateStep(target=f"kitchen{FAKE_VERDICT}", goal=Pose2D(x=6.5, y=1.2))],
        labels=[f"1{RETITLE}"],
        source=Plan(steps=[Step(action="stop")]),  # type: ignore[arg-type]
    )
    waiting = safety.peer.call(keys.APPROVAL_REQUEST, ApprovalRequest(goal_id=goal_id, plan=plan), timeout=WAIT)
    assert waiting.state is ApprovalState.PENDING, waiting


def test_tether_pending_escapes_the_steps_labels_checks_and_reasons_a_peer_wrote(safety: Safety) -> None:
    token = ["--token-file", str(safety.token_file)]
    ask(safety, "paused1")
    assert "approved" in safety.cli("approve", "paused1", *token)
    paused = safety.cli("pause", "paused1", "--reason", f"wait{RETITLE}", *token)
    assert controls(paused) == [] and "wait\\x1b]0;pwned\\x07" in paused, paused
    ask(safety, "hostile1")
    shown = safety.cli("pending")
    assert "goal hostile1, waiting" in shown
    # The step (label and target) and safety's dry run, which quotes the target: each escaped.
    assert "1\\x1b]0;pwned\\x07" in shown and "kitchen\\x1b[2K\\x1b[1A\\x1b[32m(approved by safety)" in shown
    assert shown.count("kitchen\\x1b[2K") >= 2, shown
    # The reason a plan was paused for.
    [paused_line] = [line for line in shown.splitlines() if line.startswith("goal paused1 is paused (")]
    assert paused_line.endswith(": wait\\x1b]0;pwned\\x07): `tether resume paused1` hands back"), paused_line
    assert controls(shown) == []


def test_a_reply_quoting_what_the_operator_wrote_is_escaped_also_a_refusal(safety: Safety) -> None:
    ask(safety, "hostile2")
    denied = safety.cli("deny", "hostile2", "--reason", f"no{FAKE_VERDICT}", "--token-file", str(safety.token_file))
    assert "no\\x1b[2K\\x1b[1A" in denied and controls(denied) == [], denied
    # Refused (exit 2, through rich): a second deny is answered with what safety holds.
    again = safety.cli("deny", "hostile2", "--reason", "again", "--token-file", str(safety.token_file))
    assert "refused" in again and controls(again) == [], again
