"""The whole pipeline over ROS 2 keys: the ros2 backend driving the stand-in robot, as it would a
Nav2 / ros2_control robot; the same plan, checks and recordings as on the sim."""

from __future__ import annotations

import json
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from schemas import keys
from schemas.executor import ExecutePlanGoal, PlanStatus
from schemas.world import Empty, GroundTruth
from services.recorder import scene3d
from services.runtime import stack_services
from tests.integration.conftest import LOADED_MACHINE_HEARTBEAT, Stack, start_stack, stop_stack, tether_cli
from tests.sessions import free_ports
from tether.cli import DEMO_PLAN
from tether.client import PlanSender

# Every service but the planner (no LLM here), with the ros2 backend and the stand-in for the sim.
SERVICES = tuple(s for s in stack_services("ros2-standin") if s != "planner")


def truth(stack: Stack) -> GroundTruth:
    return stack.node.call(keys.GROUND_TRUTH, Empty(), timeout=5.0)


def ros2_config(endpoint: str) -> str:
    """The backend, the stand-in robot and the recorder's ROS 2 side on one robot network."""
    return (
        f'[ros2]\nendpoint = "{endpoint}"\n{LOADED_MACHINE_HEARTBEAT}\n[ros2sim]\nlisten = "{endpoint}"\n\n'
        f'[recorder.ros2]\nendpoint = "{endpoint}"\n'
    )


def test_the_demo_plan_runs_over_ros2_keys_and_both_sides_are_recorded(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_ports()}"
    stack = start_stack(tmp_path, realtime_factor=5.0, services=SERVICES, extra_config=ros2_config(endpoint))
    try:
        cup = next(o for o in truth(stack).objects if o.id == "red_cup")
        assert cup.on == "kitchen_counter"

        run = PlanSender(stack.node).run(ExecutePlanGoal(text=DEMO_PLAN), 300.0)
        assert run.result is not None
        assert run.result.status is PlanStatus.SUCCEEDED, f"{run.result.stage}: {run.result.reason}"

        # Judged by the simulator behind the ROS 2 face, not by what the backend reported.
        after = truth(stack)
        cup = next(o for o in after.objects if o.id == "red_cup")
        assert cup.on == "coffee_table", f"the simulator has the red cup on {cup.on} at {cup.position}"
        assert after.holding is None

        status = stack.node.call(keys.RECORDER_STATUS, Empty(), timeout=3.0)
        assert status.ros2 is not None and status.ros2.path, status.ros2
        stack.supervisor.stop("recorder")

        # tether's own recording: the backend served the robot keys, so the tools work unchanged.
        topics: dict[str, int] = {}
        with open(status.path, "rb") as f:
            for _schema, channel, _message in make_reader(f).iter_messages():
                if scene3d.is_derived(channel.topic):  # the 3D scene for Foxglove, not traffic
                    continue
                path = channel.topic.split("/", 2)[2]
                topics[path] = topics.get(path, 0) + 1
        for action in ("navigate_to_pose", "follow_joint_trajectory", "gripper_command"):
            assert topics.get(f"_trace/ros2/robot/{action}/_action/send_goal"), action
        assert topics.get("robot/odom") and topics.get("robot/joint_states")
        rechecked = tether_cli(stack, "recheck", status.path, "--json")
        assert rechecked.returncode == 0, rechecked.stdout + rechecked.stderr
        report = json.loads(rechecked.stdout)
        assert report["differ"] == 0 and report["checked"] > 3, report
        inspected = tether_cli(stack, "inspect", status.path)
        assert inspected.returncode == 0, inspected.stdout + inspected.stderr
        assert "red cup" in inspected.stdout or "red_cup" in inspected.stdout, inspected.stdout
        replayed = tether_cli(stack, "replay", status.path, "--speed", "20", "--keys", "robot/odom")
        assert replayed.returncode == 0, replayed.stdout + replayed.stderr

        # The ROS 2 side, in MCAP's ros2 profile, read by Foxglove's own decoder.
        ros2_topics: dict[str, int] = {}
        odometry = []
        with open(status.ros2.path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            assert reader.get_header().profile == "ros2"
            for schema, channel, message in reader.iter_messages():
                assert schema is not None and schema.encoding == "ros2msg"
                assert channel.message_encoding == "cdr"
                ros2_topics[channel.topic] = ros2_topics.get(channel.topic, 0) + 1
                if channel.topic == "/odom" and len(odometry) < 5:
                    odometry.append(DecoderFactory().decoder_for("cdr", schema)(message.data))  # type: ignore[misc]
        assert ros2_topics.get("/odom") and ros2_topics.get("/joint_states") and ros2_topics.get("/detections")
        assert ros2_topics.get("/emergency_stop") and ros2_topics.get("/speed_limit"), ros2_topics
        assert all(o.header.frame_id == "odom" for o in odometry), [o.header.frame_id for o in odometry]
    finally:
        stop_stack(stack)
