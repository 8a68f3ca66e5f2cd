"""Test order for `make test`'s parallel run (pytest-xdist, `--dist loadscope`).

Each worker takes whole modules, in collection order, as it frees up (tests/suite.py passes
--no-loadscope-reorder: pytest-xdist would otherwise sort the modules by how many tests they hold).
The longest modules go first, so that the two workers do not end with one of them alone on a long
module. Within a module, tests keep the order they are written in (some share a stack and depend on it).
"""

from __future__ import annotations

import pytest

# The slowest modules (worker seconds in a run of the parallel part on this 2-core machine, 2026-11-27),
# longest first, unit tests among them: what comes last in collection order ends the run, and a long
# module there keeps one worker busy while the other has nothing left.
LONGEST_FIRST = (
    "tests/integration/test_tours.py",  # 118 s
    "tests/integration/test_executor.py",  # 114 s
    "tests/integration/test_recovery.py",  # 44 s
    "tests/integration/test_ros2_stack.py",  # 41 s
    "tests/integration/test_recorder.py",  # 36 s
    "tests/integration/test_modes.py",  # 33 s
    "tests/integration/test_agents.py",  # 33 s
    "tests/unit/test_sim.py",  # 28 s
    "tests/integration/test_system.py",  # 26 s
    "tests/unit/test_parser_properties.py",  # 22 s
    "tests/unit/test_manipulation.py",  # 20 s
    "tests/unit/test_grasps.py",  # 20 s
    "tests/integration/test_incidents.py",  # 18 s
    "tests/unit/test_navigation.py",  # 18 s
    "tests/unit/test_camera.py",  # 18 s
    "tests/integration/test_sim_faults.py",  # 17 s
    "tests/integration/test_resolver_world.py",  # 16 s
    "tests/integration/test_deploy_acl.py",  # 16 s
    "tests/integration/test_view.py",  # 15 s
    "tests/unit/test_sim_node.py",  # 14 s
    "tests/integration/test_cli_json.py",  # 14 s
    "tests/integration/test_caution_zone.py",  # 14 s
    "tests/integration/test_ros2_hostile.py",  # 13 s
    "tests/integration/test_sim.py",  # 9 s
    "tests/integration/test_robot_link.py",  # 9 s
    "tests/integration/test_ros2_rmw.py",  # 8 s
    "tests/integration/test_recorder_ros2.py",  # 8 s
    "tests/unit/test_linkaudit.py",  # 7 s
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    rank = {path: i for i, path in enumerate(LONGEST_FIRST)}
    root = config.rootpath

    def key(item: pytest.Item) -> int:
        return rank.get(item.path.relative_to(root).as_posix(), len(rank))

    items.sort(key=key)  # stable: the rest keep their order
