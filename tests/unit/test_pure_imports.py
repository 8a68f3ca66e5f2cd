"""Pure logic loads without the transport, and a service without the heavy packages of the others."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tether.runservice import read_command_line, runs_a_service

ROOT = Path(__file__).resolve().parents[2]

PURE = [
    "services.errors",
    "services.parser.parser",
    "services.resolver.resolver",
    "services.safety.policy",
    "services.safety.monitor",
    "services.safety.gate",
    "services.executor.runner",
    "services.robotrules",
    "services.robotlink",
    "services.repeats",
    "services.ros2.types",
    "services.ros2.wire",
    "services.ros2.backend",
    "services.ros2.goals",
    "services.ros2.config",  # the stand-in takes its ROS names from it
    "services.ros2sim.estop",
]

# One interpreter imports them one after another: each import adds only what the ones before it did
# not load, so zenoh loaded after an import was loaded by that module (one interpreter for all: each
# costs about 0.3 s of CPU to start and import, and the unit tests are CPU-bound, tests/suite.py).
CHILD = """
import importlib, json, sys
loaded = {}
for module in sys.argv[1:]:
    importlib.import_module(module)
    loaded[module] = sorted(name for name in sys.modules if name == "zenoh" or name.startswith("zenoh."))
    if loaded[module]:
        break
print(json.dumps(loaded))
"""


def python(code: str, *args: str) -> str:
    """What a fresh interpreter running `code` (from the project's root) printed; it must succeed."""
    child = subprocess.run(
        [sys.executable, "-c", code, *args], cwd=ROOT, capture_output=True, text=True, timeout=120, check=False
    )
    assert child.returncode == 0, child.stderr[-2000:]
    return child.stdout


def test_a_pure_module_does_not_load_zenoh() -> None:
    loaded = json.loads(python(CHILD, *PURE).splitlines()[-1])
    assert list(loaded) == PURE, f"importing {list(loaded)[-1]} loaded {loaded[list(loaded)[-1]]}"
    assert all(names == [] for names in loaded.values()), loaded


# A service process loads what its service uses, no more: `tether run SERVICE` (the script, as systemd
# units and containers run it) and `python -m tether run SERVICE` (as the Supervisor does) go through
# tether.runservice, not tether.cli, and the CLI's quick commands load none of the heavy packages.
# Steps in one interpreter, each adding to what the ones before loaded, so each forbids a subset of
# what the step before it did.
HEAVY = ("pinocchio", "pybullet", "ompl", "cryptography", "matplotlib", "mcp")
# typer (and its click) and pydantic, which typer 0.29 checks values with: `tether run` reads its own line.
LIGHT = (*HEAVY, "shapely", "numpy", "rich", "tether.cli", "typer", "pydantic")
LOAD_STEPS = {
    "module": [
        ("`tether run` with the parser and the planner", "services.parser.main, services.planner.main", LIGHT),
        ("the resolver", "services.resolver.main", (*HEAVY, "mcap", "rosbags", "typer", "pydantic")),
        ("tether.cli (status, send, ...)", "tether.cli", HEAVY),
    ],
    # The recorder keeps the world and policy files, by their paths only (services/bundled.py).
    "script": [
        ("`tether run` with the recorder", "services.recorder.main", LIGHT),
        # The sim's camera draws in its renderer process (services/sim/renderer.py), which alone loads Pillow.
        (
            "the sim",
            "services.sim.main",
            ("pinocchio", "ompl", "mcp", "matplotlib", "PIL", "typer", "pydantic", "tether.cli"),
        ),
        # Safety's arm model is pinocchio's; the planners (OMPL) are the executor's.
        ("safety", "services.safety.main", ("ompl", "mcp", "matplotlib", "PIL", "typer", "pydantic", "tether.cli")),
    ],
}

STEPS_CHILD = """
import contextlib, importlib.metadata, io, json, runpy, sys

entry, steps = sys.argv[1], json.loads(sys.argv[2])
# `tether run` for real: tether/__main__.py picks the module, then `run` refuses the name.
sys.argv = ["tether", "run", "no-such-service"]
with contextlib.redirect_stderr(io.StringIO()), contextlib.suppress(SystemExit):
    if entry == "module":  # python -m tether
        runpy.run_module("tether", run_name="__main__", alter_sys=True)
    else:  # the installed `tether` script: what pyproject.toml's [project.scripts] names
        (script,) = importlib.metadata.entry_points(group="console_scripts", name="tether")
        script.load()()
loaded = {}
for what, modules, forbidden in steps:
    exec("import " + modules)
    loaded[what] = [name for name in forbidden if name in sys.modules]
print(json.dumps(loaded))
"""


@pytest.mark.parametrize("entry", LOAD_STEPS)
def test_a_service_process_and_the_cli_load_no_heavy_package_they_do_not_use(entry: str) -> None:
    steps = LOAD_STEPS[entry]
    loaded = json.loads(python(STEPS_CHILD, entry, json.dumps(steps)).splitlines()[-1])
    assert loaded == {what: [] for what, _, _ in steps}, loaded


@pytest.mark.parametrize(
    ("argv", "alone"),
    [
        (["run", "parser"], True),
        (["--robot", "r1", "--base-port", "7500", "run", "sim", "--config", "x.toml"], True),
        (["--robot=r1", "--zenoh-config", "z.json5", "run", "--help"], True),
        (["--robot", "run", "status"], False),  # `run` is the robot's name here
        (["--help", "run"], False),  # the whole CLI's help
        (["status"], False),
        (["--robot", "r1"], False),
        ([], False),
    ],
)
def test_only_run_goes_to_the_small_module(argv: list[str], alone: bool) -> None:
    assert runs_a_service(argv) is alone


@pytest.mark.parametrize(
    ("argv", "line"),
    [
        (["run", "parser"], ({}, "parser", None)),
        (
            ["--robot", "r1", "--base-port", "7500", "run", "sim", "--config", "x.toml"],
            ({"--robot": "r1", "--base-port": "7500"}, "sim", Path("x.toml")),
        ),
        (
            ["--robot=r1", "--zenoh-config", "z.json5", "run", "--config=c.toml", "safety"],
            ({"--robot": "r1", "--zenoh-config": "z.json5"}, "safety", Path("c.toml")),
        ),
        (["run", "no-such-service"], ({}, "no-such-service", None)),  # run_service names the services
        # typer's: help, errors, anything not plainly one service
        (["run", "--help"], None),
        (["--help", "run"], None),
        (["run"], None),
        (["run", "parser", "safety"], None),
        (["run", "parser", "--config"], None),
        (["run", "parser", "--config", ""], None),
        (["run", "parser", "--config", "a", "--config", "b"], None),
        (["run", "parser", "--verbose"], None),
        (["--robot", "r1", "--robot", "r2", "run", "parser"], None),
        (["--robot", "--base-port", "7500", "run", "parser"], None),
        (["--base-port", "abc", "run", "parser"], None),
        (["--config", "x.toml", "run", "parser"], None),
        (["run", "parser", "--", "--config"], None),
    ],
)
def test_tether_run_reads_a_plain_command_line_itself_and_leaves_the_rest_to_typer(
    argv: list[str], line: tuple[dict[str, str], str, Path | None] | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("TETHER_BASE_PORT", raising=False)
    assert read_command_line(argv) == line


def test_a_base_port_in_the_environment_that_is_no_number_is_left_to_typer(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TETHER_BASE_PORT", "seventy")
    assert read_command_line(["run", "parser"]) is None
    monkeypatch.setenv("TETHER_BASE_PORT", "7500")
    assert read_command_line(["run", "parser"]) == ({}, "parser", None)


@pytest.mark.parametrize(
    ("argv", "code", "shown"),
    [
        # Read by tether.runservice: the error its own, in the CLI's words.
        (["run", "no-such-service"], 2, "error: unknown service 'no-such-service'; services are sim, "),
        # Left to typer (tether.runcommand): its help, and its usage errors.
        (["run", "--help"], 0, "Run one service in the foreground until SIGINT or SIGTERM."),
        (["--base-port", "abc", "run", "parser"], 2, "Invalid value"),
        (["run", "parser", "--verbose"], 2, "No such option: --verbose"),
    ],
)
def test_tether_run_answers_a_line_it_cannot_run_with_help_or_a_usage_error(
    argv: list[str], code: int, shown: str, tmp_path: Path
) -> None:
    child = subprocess.run(
        [sys.executable, "-m", "tether", *argv],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env={name: value for name, value in os.environ.items() if not name.startswith("TETHER_")},
    )
    assert child.returncode == code, child.stderr
    assert shown in " ".join((child.stdout + child.stderr).split()), child.stdout + child.stderr
