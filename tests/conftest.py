"""Test order for `make test`'s parallel run (pytest-xdist, `--dist loadscope`).

Each worker takes whole modules, in collection order, as it frees up (tests/suite.py passes
--no-loadscope-reorder: pytest-xdist would otherwise sort the modules by how many tests they hold).
The longest modules go first, so that the two workers do not end with one of them alone on a long
module. Within a module, tests keep the order they are written in (some share a stack and depend on it).
"""

from __future__ import annotations

import pytest

# The slowest modules (wall seconds on this 2-core machine, 2026-11), longest first.
LONGEST_FIRST = (
    "tests/integration/test_multihost.py",  # only in the run of the tests marked alone (tests/suite.py)
    "tests/integration/test_tours.py",
    "tests/integration/test_executor.py",
    "tests/integration/test_ros2_stack.py",
    "tests/integration/test_agents.py",
    "tests/integration/test_modes.py",
    "tests/integration/test_recovery.py",
    "tests/integration/test_system.py",
    "tests/integration/test_recorder.py",
    "tests/integration/test_incidents.py",
    "tests/integration/test_deploy_acl.py",
    "tests/integration/test_view.py",
    "tests/integration/test_sim_faults.py",
    "tests/integration/test_caution_zone.py",
    "tests/integration/test_ros2_hostile.py",
    "tests/integration/test_sim.py",
    "tests/integration/test_robot_link.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    rank = {path: i for i, path in enumerate(LONGEST_FIRST)}
    root = config.rootpath

    def key(item: pytest.Item) -> int:
        return rank.get(item.path.relative_to(root).as_posix(), len(rank))

    items.sort(key=key)  # stable: the rest keep their order
