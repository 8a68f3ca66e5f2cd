"""Invariant 1 in the secured deployment: Zenoh access control lets only safety command the robot."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_access_control_config_lets_only_safety_write_robot_commands() -> None:
    # A real router with deploy/secured.json5 and a logged-in client per user (see the script).
    done = subprocess.run(
        [sys.executable, str(ROOT / "deploy" / "check_acl.py")], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "executor may not send a robot goal" in done.stdout
    assert "safety may send a robot goal" in done.stdout
    assert "ok   ros2 may put robot/odom" in done.stdout
    assert "ok   ros2 may serve robot/**" in done.stdout
    assert "ok   executor may not serve robot/**" in done.stdout
