"""`tether view` under a hostile viewer: what one client's loop of requests costs every other viewer."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import foxglove
from foxglove.websocket import StatusLevel

from services.recorder import scene3d
from tether.view import LiveView, TeleopBridge, load_scene, teleop_loop


def wait_until(condition: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout} s: {what}"
        time.sleep(0.005)


@dataclass
class StatusServer:
    """What teleop_loop needs of the Foxglove server: the status messages it broadcasts to every viewer."""

    statuses: list[str] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def publish_status(self, message: str, level: StatusLevel, id: str | None = None) -> None:
        with self._lock:
            self.statuses.append(message)

    def told(self) -> list[str]:
        with self._lock:
            return list(self.statuses)


def test_a_client_refused_in_a_loop_costs_the_other_viewers_a_few_status_messages() -> None:
    """Each status goes to every viewer's control queue (64 deep: the SDK disconnects a viewer whose
    queue is full). A client advertising bad channels as fast as it can made the view broadcast up to
    16 statuses every 20 ms tick: a viewer lagging by a tenth of a second was disconnected."""
    bridge = TeleopBridge(lambda twist: None)
    server = StatusServer()
    stop = threading.Event()
    loop = threading.Thread(target=teleop_loop, args=(bridge, server, stop), daemon=True)
    loop.start()
    try:
        bridge.advertise(1, ChannelAd("/other", 1))  # type: ignore[arg-type]
        wait_until(lambda: bool(server.told()), "the first refusal told")
        assert "client 1 channel 1 not taken" in server.told()[0]
        flood_start = time.monotonic()
        channel = 2
        while time.monotonic() - flood_start < 1.0:
            bridge.advertise(2, ChannelAd("/other", channel))  # type: ignore[arg-type]
            channel += 1
        during = len(server.told()) - 1
        # The latest refusals are told once the flood ends, not only the first.
        latest = f"client 2 channel {channel - 1} not taken"
        wait_until(lambda: any(latest in status for status in server.told()), "the latest refusal told")
    finally:
        stop.set()
        loop.join(timeout=5.0)
    assert not loop.is_alive()
    assert channel > 100, channel  # it was a flood
    assert 1 <= during <= 4, during


@dataclass(frozen=True)
class ChannelAd:
    topic: str
    id: int
    encoding: str = "json"
    schema_name: str = "geometry_msgs/Twist"


def test_a_viewer_subscribing_to_the_scene_in_a_loop_does_not_have_it_sent_to_everyone_each_pass() -> None:
    """The static scene (about 13 KB) goes again to a viewer that subscribes; the SDK broadcasts it to every
    subscriber. A client subscribing in a loop made it go out on each 20 Hz pass, to every viewer,
    instead of every STATIC_PERIOD: a hundred times the bandwidth, pushing out other viewers' messages."""
    scene, _ = load_scene(None)
    now = [1000.0]
    live = LiveView("r", scene, foxglove.Context(), clock=lambda: now[0])
    sent: list[float] = []
    real_log = live._log

    def log(topic: str, message: scene3d.Message) -> None:
        if topic == scene3d.SCENE_TOPIC:
            sent.append(now[0])
        real_log(topic, message)

    live._log = log  # type: ignore[method-assign]
    live.publish_once()
    assert sent == [1000.0]  # at start
    now[0] += 2.0
    live.viewer_subscribed(scene3d.SCENE_TOPIC)
    live.publish_once()
    assert sent[-1] == now[0]  # a new viewer after a quiet while: at once
    for _ in range(40):  # 2 s of passes, a subscription before each
        now[0] += 0.05
        live.viewer_subscribed(scene3d.SCENE_TOPIC)
        live.publish_once()
    again = [at for at in sent if at > 1002.0]
    assert 2 <= len(again) <= 5, again
    # The last subscription is answered too, not left for STATIC_PERIOD.
    for _ in range(20):
        now[0] += 0.05
        live.publish_once()
    assert sent[-1] > 1004.0, sent
