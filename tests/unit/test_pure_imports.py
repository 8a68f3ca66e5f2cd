"""Pure logic loads without the transport: importing it in a fresh interpreter leaves zenoh out."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

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

CHILD = """
import sys
import {module}
loaded = sorted(name for name in sys.modules if name == "zenoh" or name.startswith("zenoh."))
print(" ".join(loaded))
"""


@pytest.mark.parametrize("module", PURE)
def test_a_pure_module_does_not_load_zenoh(module: str) -> None:
    child = subprocess.run(
        [sys.executable, "-c", CHILD.format(module=module)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert child.returncode == 0, child.stderr[-2000:]
    assert child.stdout.strip() == "", f"importing {module} loaded {child.stdout.strip()}"
