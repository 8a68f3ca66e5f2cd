"""Review 46 of the CLI: `tether mcp --port` out of range and the demo's config with any directory name."""

from __future__ import annotations

import tomllib
from pathlib import Path

import typer
from typer.testing import CliRunner

from tether.cli import demo_config, mcp_command

USAGE = 2


def test_mcp_refuses_a_port_out_of_range_naming_it() -> None:
    # Taken, --port 70000 went as far as binding the socket: a 125-line traceback (OverflowError), exit 1.
    app = typer.Typer()
    app.command()(mcp_command)
    result = CliRunner().invoke(app, ["--http", "--port", "70000"])
    output = " ".join(result.output.replace("\u2502", " ").split())
    assert result.exit_code == USAGE, output
    assert "Invalid value for '--port': 70000 is not in the range 1<=x<=65535" in output, output


def test_the_demo_config_names_a_recordings_directory_with_quotes_and_backslashes_as_it_is(tmp_path: Path) -> None:
    # Written between quotes as it was, such a name made a file TOML cannot read, or another directory.
    recordings = tmp_path / 'my "demo" runs\\2026'
    for endpoint in (None, "tcp/127.0.0.1:7499"):
        config = tomllib.loads(demo_config(2.0, recordings, endpoint))
        assert config["recorder"]["output_dir"] == str(recordings)
        assert config["sim"]["realtime_factor"] == 2.0
        if endpoint is not None:
            assert config["ros2"]["endpoint"] == config["ros2sim"]["listen"] == endpoint
            assert config["recorder"]["ros2"]["endpoint"] == endpoint
