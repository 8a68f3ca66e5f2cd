"""The stop, safety's heartbeat and the twist safety lets through go at Zenoh's real-time priority,
blocking rather than dropped on a congested link: sent as data (Zenoh's default, dropped when a link's
queue is full), a camera stream or a recording's flood could hold up or lose an e-stop."""

from __future__ import annotations

import queue
import uuid

import zenoh

from schemas import keys
from schemas.robot import Twist
from schemas.safety import EStop, EstopState, SafetyStatus
from services.runtime import Node, NodeSettings
from tests.sessions import free_port

WAIT = 10.0


def test_urgent_topics_are_sent_real_time_and_never_dropped_and_the_others_as_data() -> None:
    settings = NodeSettings(robot=f"t{uuid.uuid4().hex[:8]}", base_port=free_port())
    heard: queue.SimpleQueue[zenoh.Sample] = queue.SimpleQueue()
    with Node("sim", settings) as listener, Node("safety", settings) as sender:
        subscriber = listener.session.declare_subscriber(f"{keys.prefix(settings.robot)}/**", heard.put)
        try:
            beat = sender.publisher(keys.HEARTBEAT)
            sender.publish(keys.ESTOP, EStop(source="operator", reason="test"))
            beat.put(SafetyStatus(seq=1, stamp=0.0, estop=EstopState(latched=True)))
            sender.publish(keys.ROBOT_CMD_VEL, Twist())
            sender.publish(keys.CMD_VEL, Twist())
            samples = {}
            while len(samples) < 4:
                sample = heard.get(timeout=WAIT)
                samples[str(sample.key_expr).removeprefix(keys.prefix(settings.robot) + "/")] = sample
        finally:
            subscriber.undeclare()
    for path in (keys.ESTOP.path, keys.HEARTBEAT.path, keys.ROBOT_CMD_VEL.path):
        sample = samples[path]
        assert (sample.priority, sample.congestion_control) == (
            zenoh.Priority.REAL_TIME,
            zenoh.CongestionControl.BLOCK,
        ), path
        assert sample.express, path
    data = samples[keys.CMD_VEL.path]
    assert (data.priority, data.congestion_control) == (zenoh.Priority.DATA, zenoh.CongestionControl.DROP)
