"""The router's rules from `tether deploy init`, read as the router reads them: who may put, serve and ask each key."""

from __future__ import annotations

from typing import Any

import pytest
import zenoh

from schemas import keys
from tether import deployment

ROBOT = "r1"
ROOT = f"tether/{ROBOT}/"


def _control() -> tuple[dict[str, dict[str, Any]], list[dict[str, Any]]]:
    rules, _, policies = deployment.access_rules(ROBOT, tls=False)
    return {r["id"]: r for r in rules}, policies


def may(identity: str, message: str, path: str) -> bool:
    """Whether a rule of `identity`'s policies lets `message` on ROOT + `path` into the router (ingress)."""
    rules, policies = _control()
    key = zenoh.KeyExpr(ROOT + path)
    user = deployment.username(ROBOT, identity)
    return any(
        message in rules[name]["messages"] and any(zenoh.KeyExpr(k).includes(key) for k in rules[name]["key_exprs"])
        for p in policies
        if user in p["subjects"]
        for name in p["rules"]
        if rules[name]["flows"] == ["ingress"]
    )


def who(message: str, path: str) -> list[str]:
    return [i for i in deployment.IDENTITIES if may(i, message, path)]


def test_every_key_of_the_contract_has_its_owners_and_nothing_else_is_granted() -> None:
    # A new key in schemas/keys.py is denied in a deployment until it is granted in OWNERS: this names it.
    assert set(deployment.OWNERS) == set(deployment.declared_keys()) - {
        s.path
        for a in keys.ACTIONS
        for s in (a.send_goal, a.cancel_goal, a.get_result, a.get_status, a.feedback, a.status)
    }
    for path in ("plan/marker", "planner/notes", "sim/teleport", "cmd/anything", "recorder/stop", "bench/raw_relay"):
        for message in ("put", "query", "declare_queryable"):
            assert who(message, path) == [], (message, path)


def test_an_owner_names_only_identities_and_a_topic_is_never_asked() -> None:
    declared = deployment.declared_keys()
    for path, owners in deployment.OWNERS.items():
        assert owners.by and set(owners.by + owners.asked_by) <= set(deployment.IDENTITIES), path
        if isinstance(declared[path], keys.Topic):
            assert owners.asked_by == (), path


@pytest.mark.parametrize(
    ("path", "publishers"),
    [
        # What the review forged: a plan's status (safety ends an approval on it), a command's status, the
        # planner's attempts; each published by its owner alone.
        (keys.EXECUTE_PLAN.status.path, ["executor"]),
        (keys.EXECUTE_PLAN.feedback.path, ["executor"]),
        (keys.CMD_NAVIGATE.status.path, ["safety"]),
        (keys.CMD_TRAJECTORY.feedback.path, ["safety"]),
        (keys.CMD_GRIPPER.status.path, ["safety"]),
        (keys.PLANNER_ATTEMPTS.path, ["planner"]),
        (keys.PLANNER_RECOVERIES.path, ["planner"]),
        (keys.ROBOT_NAVIGATE.status.path, ["sim", "ros2"]),
        (keys.HEARTBEAT.path, ["safety"]),
        (keys.CMD_VEL.path, ["executor", "operator"]),
        (keys.TELEOP_CMD_VEL.path, ["operator"]),
        (keys.HUMANS.path, ["sim", "ros2"]),
    ],
)
def test_each_publication_is_put_by_its_owner_alone(path: str, publishers: list[str]) -> None:
    assert who("put", path) == publishers
    assert who("delete", path) == publishers


def test_the_review_s_forgeries_are_denied() -> None:
    assert not may("parser", "put", "plan/execute/_action/status")
    assert not may("parser", "put", "cmd/navigate_to_pose/_action/status")
    assert not may("recorder", "put", "cmd/navigate_to_pose/_action/feedback")
    assert not may("recorder", "put", "planner/attempts")
    assert not may("recorder", "query", "sim/move")
    for identity in ("parser", "planner", "resolver", "recorder", "agent", "sim"):
        for action in (keys.CMD_NAVIGATE, keys.CMD_TRAJECTORY, keys.CMD_GRIPPER):
            assert not may(identity, "query", action.send_goal.path), (identity, action.path)


@pytest.mark.parametrize(
    ("path", "servers", "askers"),
    [
        (keys.PLAN_PARSE.path, ["parser"], ["executor"]),
        (keys.PLAN_RESOLVE.path, ["resolver"], ["executor"]),
        (keys.PLAN_ASK.path, ["planner"], ["operator", "agent"]),
        (keys.PLAN_ASK_CANCEL.path, ["planner"], ["operator", "agent"]),
        (keys.EXECUTE_PLAN.send_goal.path, ["executor"], ["planner", "operator", "agent"]),
        (keys.CMD_NAVIGATE.send_goal.path, ["safety"], ["executor", "operator"]),
        (keys.CMD_GRIPPER.cancel_goal.path, ["safety"], ["executor", "operator"]),
        (keys.ROBOT_TRAJECTORY.send_goal.path, ["sim", "ros2"], ["safety"]),
        (keys.RESET.path, ["safety"], ["operator"]),
        (keys.APPROVAL_REQUEST.path, ["safety"], ["executor"]),
        (keys.SIM_MOVE.path, ["sim"], ["operator"]),
        (keys.RECORDER_STATUS.path, ["recorder"], ["safety", "operator"]),
        (keys.SCENE.path, ["resolver"], ["executor", "planner", "operator", "agent"]),
    ],
)
def test_each_service_is_served_by_its_owner_and_asked_by_its_callers(
    path: str, servers: list[str], askers: list[str]
) -> None:
    assert who("declare_queryable", path) == servers
    assert who("reply", path) == servers
    assert who("query", path) == askers


def test_a_grant_of_a_key_the_contract_does_not_define_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(deployment.OWNERS, "plan/forged", deployment.Owners(("parser",)))
    with pytest.raises(deployment.DeploymentError, match="plan/forged"):
        deployment.access_rules(ROBOT, tls=False)
