"""The robot's side: Zenoh access control on the ROS 2 robot's router lets only tether command the robot."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_robot_router_config_lets_only_tether_write_robot_commands() -> None:
    # A real router with deploy/ros2-router.json5, the robot's node, tether and an intruder (see the script).
    done = subprocess.run(
        [sys.executable, str(ROOT / "deploy" / "check_ros2_acl.py")], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "ok   tether may put cmd_vel" in done.stdout
    assert "ok   intruder may not put cmd_vel" in done.stdout
    assert "ok   intruder may not query navigate_to_pose/_action/send_goal (never arrives, no reply)" in done.stdout
    assert "ok   the robot's odom reaches tether" in done.stdout
