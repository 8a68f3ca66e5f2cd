"""Test order for `make test`'s parallel runs (pytest-xdist, `--dist loadscope`), and the `unit` marker.

Every test under tests/unit is marked `unit`, and those of IDLE_UNIT's modules `idle` too, for
tests/suite.py to select.

Each worker takes whole modules as it frees up. pytest-xdist's loadscope (3.5 and later) hands them
out by how many tests they hold, most first, and this order decides only among modules of equal
count (and in runs without pytest-xdist). Keeping this order instead (--no-loadscope-reorder) was
tried on 2026-11-27: it put the heaviest stacks (the tours, the executor's, the ROS 2 stack's) beside
the wall-clock tests at the start, the fresh-clone parallel part took 395.1 s against 395.3 s, and
a wall-clock teleop test then failed once under that load. Within a module, tests keep the order
they are written in (some share a stack and depend on it).
"""

from __future__ import annotations

import signal

import pytest

# Every test under it is marked `unit`: its work is done in the pytest process or in children it
# starts itself, without a stack of services (`make test` runs these beside the tests marked alone,
# tests/suite.py).
UNIT = "tests/unit"

# Where `make test`'s run of the tests marked realtime (and not alone) looks for them (tests/suite.py
# ROOTS): the modules of tests/unit that have some, and the integration tests. A test marked so
# anywhere else is refused here, not left out of that run.
REALTIME_UNIT = ("tests/unit/test_planner.py", "tests/unit/test_runtime_serve.py")
INTEGRATION = "tests/integration"

# Modules of tests/unit whose tests only compute: no wall-clock bound or deadline (a bound on work is
# on CPU time, time.thread_time), no planner's time limit, no service, thread or clock to wait on.
# Their tests are marked `idle` too: `make test` runs them from the start in a scheduling group of the
# lowest weight, under SCHED_IDLE in it, on the CPU the stacks leave (tests/suite.py), however long
# they wait for it. A module that starts to wait on
# the clock leaves this list.
IDLE_UNIT = (
    "tests/unit/test_parser_properties.py",
    "tests/unit/test_parser_text.py",
    "tests/unit/test_parser_shapes.py",
    "tests/unit/test_parser_corpus.py",
    "tests/unit/test_parser.py",
    "tests/unit/test_linkaudit.py",
    "tests/unit/test_shared_filter.py",
    "tests/unit/test_timeline.py",
    "tests/unit/test_tool_schemas.py",
    "tests/unit/test_ros2_wire.py",
    "tests/unit/test_robot_keepout.py",
    "tests/unit/test_deployment.py",
)

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
    unit = root / UNIT
    for item in items:
        alone = item.get_closest_marker("alone") is not None
        realtime = item.get_closest_marker("realtime") is not None and not alone
        looked_at = item.path.relative_to(root).as_posix() in REALTIME_UNIT or item.path.is_relative_to(
            root / INTEGRATION
        )
        if realtime and not looked_at:
            raise pytest.UsageError(
                f"{item.nodeid}: a test marked realtime lives in {INTEGRATION} or in a module of REALTIME_UNIT"
                " (tests/conftest.py), where `make test` looks for them"
            )
        if item.path.is_relative_to(unit):
            if alone:
                # `make test` runs the tests marked alone without collecting tests/unit (tests/suite.py ROOTS).
                raise pytest.UsageError(f"{item.nodeid}: a test under {UNIT} is never marked alone")
            item.add_marker(pytest.mark.unit)
            if item.path.relative_to(root).as_posix() in IDLE_UNIT:
                item.add_marker(pytest.mark.idle)


def pytest_configure(config: pytest.Config) -> None:
    # Tests interrupt tether commands with SIGINT, as a Ctrl-C does. A run started with SIGINT ignored
    # (`nohup make test &`, a background job of a shell without job control) handed that on to every
    # process it started, and a Python started with SIGINT ignored never raises KeyboardInterrupt:
    # each such test waited out its deadline (ten failed in one run). With a handler here, the
    # children start with the default again (an exec resets handled signals, not ignored ones).
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
