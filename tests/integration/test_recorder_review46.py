"""`tether replay` as a real process over real Zenoh: a service coming up under the replay's name stops it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

from schemas import keys
from schemas.robot import Twist
from services.recorder.mcapfile import Recording
from services.runtime import ALL_SERVICES, Node, NodeSettings, encode
from tests.sessions import free_ports

RECORDED = "incident"
TWISTS = 200  # every 0.05 s: 10 s of driving
DEADLINE = 20.0


def driving(path: Path) -> Path:
    """Safety's twists to the robot's driver (robot/cmd_vel), as recorded."""
    file = Recording(path, RECORDED)
    for i in range(TWISTS):
        key = keys.ROBOT_CMD_VEL.key(RECORDED)
        file.record(key, encode(Twist(linear_x=0.3)), log_time=int((1000.0 + i * 0.05) * 1e9))
    file.finish()
    return path


def test_a_replay_stops_when_a_driver_comes_up_under_its_name(tmp_path: Path) -> None:
    """The name was checked for live services once, at the start: a sim or driver started under it
    during the replay was then driven by the recorded robot/cmd_vel, with no safety, to the end."""
    file = driving(tmp_path / "drive.mcap")
    target = NodeSettings(robot=f"{RECORDED}_replay", base_port=free_ports(len(ALL_SERVICES)))
    heard = threading.Condition()
    twists: list[int] = []  # how many were heard before each one: counted since the driver came up
    env = {**os.environ, "TETHER_BASE_PORT": str(target.base_port)}
    env.pop("TETHER_ZENOH_CONFIG", None)
    env.pop("TETHER_ROBOT", None)

    def on_twist(_twist: Twist) -> None:
        with heard:
            twists.append(len(twists))
            heard.notify_all()

    command = [sys.executable, "-m", "tether", "replay", str(file), "--no-progress"]
    with Node("sim", target) as driver:
        driver.subscribe(keys.ROBOT_CMD_VEL, on_twist)
        process = subprocess.Popen(command, env=env, stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            with heard:
                assert heard.wait_for(lambda: twists, timeout=DEADLINE), "the replay put nothing"
                driver.declare_alive()
                came_up = len(twists)
            _, stderr = process.communicate(timeout=DEADLINE)
        finally:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
        with heard:
            after = len(twists) - came_up
    said = " ".join(stderr.split())
    assert process.returncode == 2, stderr
    assert f"robot {target.robot}'s sim came up during the replay" in said, stderr
    assert after < TWISTS // 4, f"{after} twists were replayed to the driver after it came up"
