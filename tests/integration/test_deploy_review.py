"""A robot's backend (`tether deploy init --backend`), proven with its real router and client files."""

from __future__ import annotations

import contextlib
import os
import queue
import socket
import time
from pathlib import Path

import pytest
import zenoh

from services.runtime import zenoh_config_file
from tests.sessions import free_port
from tether import deployment

DEADLINE = 10.0
ODOM = "tether/r1/robot/odom"


def logs_in(conf: zenoh.Config) -> bool:
    conf.insert_json5("connect/timeout_ms", "0")
    conf.insert_json5("connect/exit_on_failure", "true")
    try:
        zenoh.open(conf).close()
    except zenoh.ZError:
        return False
    return True


def test_a_robot_narrowed_to_ros2_refuses_its_old_sim_identity(tmp_path: Path) -> None:
    zenoh.init_log_from_env_or("off")  # the refused login logs an error by design
    directory = tmp_path / "deploy"
    deployment.init(directory, ["r1"], router=deployment.RouterAddress("127.0.0.1", free_port()))
    old_sim = tmp_path / "sim.json5"  # the sim identity's config, as installed before
    old_sim.write_bytes((directory / "r1" / "sim.json5").read_bytes())
    deployment.init(directory, ["r1"], backend="ros2")
    seen: queue.Queue[bytes] = queue.Queue()
    with (
        zenoh.open(zenoh_config_file(directory / deployment.ROUTER_CONFIG)) as router,
        router.declare_subscriber(ODOM, lambda sample: seen.put(sample.payload.to_bytes())),
    ):
        assert not logs_in(zenoh_config_file(old_sim)), "the sim identity of a ros2 robot logged in"
        ros2 = zenoh_config_file(directory / "r1" / "ros2.json5")
        assert logs_in(ros2)
        # And the robot's own backend still reports its state through this router.
        with zenoh.open(ros2) as session:
            nonce = os.urandom(8)
            deadline = time.monotonic() + DEADLINE
            got = b""
            while got != nonce:
                assert time.monotonic() < deadline, "the ros2 identity's odometry never reached the router"
                session.put(ODOM, nonce)
                with contextlib.suppress(queue.Empty):
                    got = seen.get(timeout=0.1)


def ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
    except OSError:
        return False
    return True


@pytest.mark.skipif(not ipv6_loopback(), reason="no IPv6 loopback here")
def test_a_router_at_an_ipv6_address_lets_its_clients_in(tmp_path: Path) -> None:
    zenoh.init_log_from_env_or("off")
    deployment.init(tmp_path, ["r1"], router=deployment.RouterAddress("::1", free_port()))
    with zenoh.open(zenoh_config_file(tmp_path / deployment.ROUTER_CONFIG)):
        assert logs_in(zenoh_config_file(tmp_path / "r1" / "operator.json5"))
