"""`tether view` against what a robot may send: a stamp Foxglove's time cannot carry is shown as the nearest
it can, and the view goes on showing the robot to a Foxglove client (@foxglove/ws-protocol,
tests/integration/foxglove_client); the URL it gives for an IPv6 host is one that client opens."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from schemas import keys
from schemas.common import Pose2D
from schemas.robot import Odometry
from services.recorder import scene3d
from services.runtime import Node
from tests.integration.conftest import Stack, start_stack, stop_stack
from tests.integration.test_view import Client, client_script, running_view

DEADLINE = 30.0


@pytest.fixture
def stack(tmp_path: Path) -> Iterator[Stack]:
    """No services: the test is the robot."""
    s = start_stack(tmp_path, 1.0, services=())
    try:
        yield s
    finally:
        stop_stack(s)


def odometry(stamp: float, x: float) -> Odometry:
    return Odometry(stamp=stamp, sim_time=0.0, pose=Pose2D(x=x, y=0.5), linear_x=0.0, angular_z=0.0)


def test_an_odometry_stamped_beyond_foxglove_time_is_shown_and_the_view_goes_on_showing_the_robot(
    stack: Stack,
) -> None:
    script = client_script()
    log_path = stack.tmp / "view.log"
    clients: list[Client] = []
    # The robot's session, where the view looks for the sim's: what it publishes is the robot's odometry.
    with (
        Node("sim", stack.settings) as robot,
        running_view(stack, ["--port", "0", "--no-arm", "--camera-rate", "0"], log_path) as (view, started),
    ):
        try:

            def first_frame(stamp: float, x: float) -> dict[str, Any]:
                """The first frame a new Foxglove client sees while the robot says it is at `x`."""
                client = Client.start(script, "watch", started["url"], str(DEADLINE), scene3d.TF_TOPIC)
                clients.append(client)
                shown = False
                while not shown and not client.ended and view.poll() is None:
                    robot.publish(keys.ODOM, odometry(stamp, x))
                    shown = client.wait_for(lambda lines: any("done" in line for line in lines), 0.5)
                ended = f"tether view ended (exit {view.returncode}):\n{log_path.read_text()[-3000:]}"
                assert view.poll() is None, ended
                assert {"done": "all"} in client.lines, client.lines[-5:]
                [frame] = client.messages(scene3d.TF_TOPIC)[0]["transforms"]
                return dict(frame)

            # A stamp of -1e300 s: valid JSON, a valid Odometry, and beyond a float in nanoseconds. The view
            # ended on it (OverflowError out of its publishing loop): the operator lost the robot's picture.
            hostile = first_frame(-1e300, 9.0)
            assert (hostile["translation"]["x"], hostile["timestamp"]) == (9.0, {"sec": 0, "nsec": 0}), hostile
            # And the next odometry is shown: the base where it says.
            frame = first_frame(5.0, 2.0)
            assert (frame["translation"]["x"], frame["translation"]["y"]) == (2.0, 0.5)
        finally:
            for client in clients:
                client.close()


def test_the_url_the_view_gives_for_ipv6_loopback_is_one_a_foxglove_client_opens(stack: Stack) -> None:
    script = client_script()
    args = ["--host", "::1", "--port", "0", "--no-arm", "--camera-rate", "0"]
    with running_view(stack, args, stack.tmp / "view.log") as (_view, started):
        # It said ws://::1:PORT, which no WebSocket client takes for an address.
        assert started["url"] == f"ws://[::1]:{started['port']}", started
        client = Client.start(script, "watch", started["url"], str(DEADLINE), scene3d.SCENE_TOPIC)
        try:
            assert client.wait_for(lambda lines: any("done" in line for line in lines))
            assert {"done": "all"} in client.lines, client.lines[-5:]
        finally:
            client.close()
