"""`tether view` and `tether teleop` with hostile input: the numbers of their options (refused at parse,
naming the option, unless finite and in range: click's min and max let "nan" through), and what the
robot sends that the view cannot make into Foxglove's messages (dropped and named, the view serving on)."""

from __future__ import annotations

import json
import logging
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import foxglove
import msgspec
import pytest
import typer
from mcap.reader import make_reader
from typer.testing import CliRunner

from schemas import keys
from schemas.actions import GoalState, GoalStatus
from schemas.common import Pose2D
from schemas.robot import Odometry
from schemas.safety import Decision, SafetyEvent
from schemas.world import CameraImage, PerceivedHumans
from services.recorder import scene3d
from services.runtime import NodeSettings
from tests.sessions import free_port
from tether import client
from tether.teleop import Deadman, drive, teleop
from tether.view import LiveView, inputs, load_scene, view

USAGE = 2


def invoke(command: Callable[..., Any], args: list[str]) -> tuple[int, str]:
    app = typer.Typer()
    app.command()(command)
    result = CliRunner().invoke(app, args)
    # The error as one line: typer draws it in a box, wrapped to the terminal's width.
    return result.exit_code, " ".join(result.output.replace("\u2502", " ").split())


@pytest.mark.parametrize("option", ["--linear", "--angular", "--scale"])
def test_teleop_refuses_a_speed_that_is_not_a_number(option: str) -> None:
    # Taken, NaN went out as null in every twist: safety could read none, the line showed "cmd +nan".
    code, output = invoke(teleop, [option, "nan"])
    assert code == USAGE and f"Invalid value for '{option}': nan is not a number" in output, output


@pytest.mark.parametrize(
    ("args", "why"),
    [
        (["--camera-rate", "nan"], "Invalid value for '--camera-rate': nan is not a number"),
        (["--port", "70000"], "Invalid value for '--port': 70000 is not in the range 0<=x<=65535"),
        (["--port", "-1"], "Invalid value for '--port': -1 is not in the range 0<=x<=65535"),
    ],
)
def test_view_refuses_a_camera_rate_or_port_out_of_bounds_naming_it(args: list[str], why: str) -> None:
    # Beyond loopback without --allow-remote: an option taken would reach that refusal instead, before
    # any session or server. Taken, --port 70000 came back as exit 1, "cannot serve on
    # 127.0.0.1:70000: number too large to fit in target type", and a NaN camera rate as no camera.
    code, output = invoke(view, [*args, "--host", "0.0.0.0"])
    assert code == USAGE and why in output, output


# What the robot sends, made into Foxglove's messages: a stamp Foxglove's time cannot hold is the nearest
# it can (services/recorder/scene3d.stamp); a message that still cannot be made is dropped, not the view.

HUGE = -1e300  # a JSON number like any other; in nanoseconds, beyond a float


def recorded(path: Path) -> dict[str, list[dict[str, Any]]]:
    """The messages the view logged, by topic, as the SDK wrote them (its MCAP sink)."""
    found: dict[str, list[dict[str, Any]]] = {}
    with path.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            found.setdefault(channel.topic, []).append(json.loads(message.data))
    return found


@dataclass
class Viewed:
    """A view logging to an MCAP file (`writer`: close it to read the file) in the SDK's `context`, which
    must live as long as the view's channels log; `receive(kind, message)` hands it a robot's message."""

    live: LiveView
    receive: Callable[[str, Any], None]
    writer: Any
    context: foxglove.Context


def live_view(path: Path) -> Viewed:
    scene, _ = load_scene(None)
    context = foxglove.Context()
    writer = foxglove.open_mcap(path, context=context)
    live = LiveView("r1", scene, context, clock=lambda: 1000.0)
    sources = {source.kind: source for source in inputs("r1")}

    def receive(kind: str, message: Any) -> None:
        live.receive(sources[kind], sources[kind].key_expr, msgspec.json.encode(message))

    return Viewed(live, receive, writer, context)


def test_messages_stamped_beyond_foxglove_time_are_shown_at_the_nearest_time(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    viewed = live_view(tmp_path / "view.mcap")
    live, receive, writer = viewed.live, viewed.receive, viewed.writer
    pose = Pose2D(x=1.0, y=2.0)
    receive("odom", Odometry(stamp=HUGE, sim_time=0.0, pose=pose, linear_x=0.0, angular_z=0.0))
    receive("humans", PerceivedHumans(stamp=HUGE, humans=[]))
    receive("safety", SafetyEvent(stamp=-HUGE, key="robot/cmd_vel", decision=Decision.APPROVED))
    receive("plan", GoalStatus(goal_id="g" * 8, state=GoalState.SUCCEEDED, stamp=HUGE))
    with caplog.at_level(logging.WARNING, logger="tether.view"):
        live.publish_once()  # raised OverflowError: the view's publishing loop, and the view, ended
    assert not [r.getMessage() for r in caplog.records if "messages not shown" in r.getMessage()]
    writer.close()
    shown = recorded(tmp_path / "view.mcap")
    [frames] = shown[scene3d.TF_TOPIC]
    assert [t["timestamp"] for t in frames["transforms"]] == [{"sec": 0, "nsec": 0}]
    [event, plan] = shown[scene3d.LOG_TOPIC]
    assert event["timestamp"] == {"sec": scene3d.MAX_STAMP_SEC, "nsec": 999_999_999}
    assert plan["timestamp"] == {"sec": 0, "nsec": 0}
    assert len(shown[keys.EXECUTE_PLAN.status.key("r1")]) == 1 and scene3d.PEOPLE_TOPIC in shown


def test_a_message_the_view_cannot_show_is_dropped_and_named_and_the_view_goes_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    viewed = live_view(tmp_path / "view.mcap")
    live, receive, writer = viewed.live, viewed.receive, viewed.writer

    def cannot(_message: Any) -> Any:
        raise ValueError("no Foxglove message holds this")

    with monkeypatch.context() as patched:  # a conversion that fails, whatever the data hit in it
        patched.setattr(scene3d, "safety_log", cannot)
        receive("safety", SafetyEvent(stamp=1.0, key="robot/cmd_vel", decision=Decision.APPROVED))
        with caplog.at_level(logging.WARNING, logger="tether.view"):
            live.publish_once()
    notes = [r.getMessage() for r in caplog.records if "messages not shown" in r.getMessage()]
    safety_key = keys.SAFETY_EVENTS.key("r1")
    assert notes == [f"messages not shown on {safety_key}: safety: ValueError: no Foxglove message holds this"]
    receive("safety", SafetyEvent(stamp=5.0, key="robot/cmd_vel", decision=Decision.APPROVED))
    live.publish_once()
    writer.close()
    assert [m["message"] for m in recorded(tmp_path / "view.mcap")[scene3d.LOG_TOPIC]] == ["approved robot/cmd_vel"]


class Camera:
    """The one call publish_camera makes, answered with `image`."""

    def __init__(self, image: CameraImage) -> None:
        self.image = image

    def call(self, service: Any, request: Any, timeout: float) -> CameraImage:
        return self.image


def test_a_camera_picture_the_view_cannot_show_does_not_end_the_camera(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    viewed = live_view(tmp_path / "view.mcap")
    live, writer = viewed.live, viewed.writer
    camera = Camera(CameraImage(stamp=HUGE, width=1, height=1, data="iVBORw0KGgo="))
    live.publish_camera(camera)  # type: ignore[arg-type]  # raised: the camera's thread ended for good
    with monkeypatch.context() as patched:
        patched.setattr(scene3d, "camera_image", lambda _image: (_ for _ in ()).throw(ValueError("cannot")))
        live.publish_camera(camera)  # type: ignore[arg-type]
    camera.image = msgspec.structs.replace(camera.image, stamp=5.0)
    live.publish_camera(camera)  # type: ignore[arg-type]
    writer.close()
    pictures = recorded(tmp_path / "view.mcap")[scene3d.CAMERA_TOPIC]
    assert [p["timestamp"] for p in pictures] == [{"sec": 0, "nsec": 0}, {"sec": 5, "nsec": 0}]


def test_ctrl_c_while_teleop_waits_for_safety_ends_it_with_its_summary(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """It left with a traceback and exit 130, no JSON object, though nothing had been sent."""

    def interrupted(_node: Any, _timeout: float) -> Any:
        raise KeyboardInterrupt  # Ctrl-C during the wait for safety's first heartbeat

    monkeypatch.setattr(client, "next_heartbeat", interrupted)
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    code = drive(SimpleNamespace(obj=settings), Deadman(), None, False, True)  # type: ignore[arg-type]
    summary = json.loads(capsys.readouterr().out)
    assert code == 0 and summary["ended"] == "SIGINT" and summary["twists_sent"] == 0, summary
