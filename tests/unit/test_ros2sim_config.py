"""The stand-in's config: `[ros2sim]` validated at start, the ROS domain from the environment first."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.ros2.wire import Style
from services.ros2sim.config import Ros2SimConfig, domain_id
from services.runtime import ConfigError, load_config
from services.sim.config import SimConfig


def test_defaults_listen_where_rmw_zenohs_router_would() -> None:
    config = load_config(Ros2SimConfig, None, "ros2sim")
    assert config.listen == "tcp/127.0.0.1:7447"
    assert (config.style, config.stamped_cmd_vel, config.cmd_vel_timeout, config.camera_hz) == (
        Style.RMW_ZENOH,
        False,
        0.5,
        1.0,
    )
    assert config.stop_timeout == 0.5  # on: the backend sends emergency_stop at 20 Hz


def test_one_file_drives_the_sim_and_its_stand_in(tmp_path: Path) -> None:
    path = tmp_path / "tether.toml"
    path.write_text('[sim]\nrealtime_factor = 2.0\n\n[ros2sim]\nlisten = "tcp/127.0.0.1:9000"\nstyle = "bridge"\n')
    assert load_config(SimConfig, path, "sim").realtime_factor == 2.0
    config = load_config(Ros2SimConfig, path, "ros2sim")
    assert (config.listen, config.style) == ("tcp/127.0.0.1:9000", Style.BRIDGE)


@pytest.mark.parametrize(
    ("table", "named"),
    [
        ("heartbeat_timeout = 0.2", "heartbeat_timeout"),  # the sim's, not the stand-in's: it has no heartbeat
        ('style = "dds"', r"\$\.style"),
        ('listen = "127.0.0.1:7447"', r"\$\.listen"),
        ("domain_id = 300", r"\$\.domain_id"),
        ("cmd_vel_timeout = 0", r"\$\.cmd_vel_timeout"),
        ("cmd_vel_timeout = 5", r"\$\.cmd_vel_timeout"),  # longer than safety checked the path for
        ("stop_timeout = -0.5", r"\$\.stop_timeout"),
    ],
)
def test_a_bad_value_is_refused_naming_it_and_the_file(tmp_path: Path, table: str, named: str) -> None:
    path = tmp_path / "tether.toml"
    path.write_text(f"[ros2sim]\n{table}\n")
    with pytest.raises(ConfigError, match=named) as refused:
        load_config(Ros2SimConfig, path, "ros2sim")
    assert str(path) in str(refused.value)


def test_ros_domain_id_in_the_environment_wins_then_the_config_then_0() -> None:
    assert domain_id(Ros2SimConfig(), {}) == 0
    assert domain_id(Ros2SimConfig(domain_id=5), {}) == 5
    assert domain_id(Ros2SimConfig(domain_id=5), {"ROS_DOMAIN_ID": "12"}) == 12
    assert domain_id(Ros2SimConfig(domain_id=5), {"ROS_DOMAIN_ID": " "}) == 5
    for bad in ("twelve", "-1", "233"):
        with pytest.raises(ConfigError, match=f"ROS_DOMAIN_ID='{bad}'"):
            domain_id(Ros2SimConfig(), {"ROS_DOMAIN_ID": bad})
