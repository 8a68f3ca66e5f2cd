"""Who may change the control mode and decide on plans: the operator's identity only, by the deployment's
access rules, and no agent path (MCP tools, the agent API, the planner) names those keys."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from schemas import keys
from services.runtime import zenoh_config_file
from tether import deployment


def may(control: dict[str, list[dict[str, object]]], identity: str, message: str, key: str) -> bool:
    """Whether the router's rules let `identity` of robot r1 send `message` on `key` (deny by default)."""
    rules = {r["id"]: r for r in control["rules"]}
    subject = deployment.username("r1", identity)
    wanted = zenoh.KeyExpr(key)
    for policy in control["policies"]:
        if subject not in policy["subjects"]:  # type: ignore[operator]
            continue
        for name in policy["rules"]:  # type: ignore[union-attr]
            rule = rules[name]
            if rule["permission"] != "allow" or "ingress" not in rule["flows"] or message not in rule["messages"]:  # type: ignore[operator]
                continue
            if any(zenoh.KeyExpr(k).includes(wanted) for k in rule["key_exprs"]):  # type: ignore[union-attr]
                return True
    return False


@pytest.fixture(scope="module")
def control(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[dict[str, object]]]:
    directory = tmp_path_factory.mktemp("deploy")
    deployment.init(directory, ["r1"])
    loaded: dict[str, list[dict[str, object]]] = json.loads(
        zenoh_config_file(directory / "router.json5").get_json("access_control")
    )
    assert loaded["default_permission"] == "deny"  # type: ignore[comparison-overlap]
    return loaded


OPERATOR_ONLY = (keys.SET_MODE, keys.APPROVAL_DECIDE, keys.RESET, keys.FORGET_INCIDENT)


@pytest.mark.parametrize("service", OPERATOR_ONLY, ids=lambda s: s.path)
def test_only_the_operator_may_set_the_mode_decide_on_plans_or_reset(
    control: dict[str, list[dict[str, object]]], service: keys.Service[object, object]
) -> None:
    key = service.key("r1")
    allowed = {i for i in deployment.IDENTITIES if may(control, i, "query", key)}
    assert allowed == {"operator"}
    # Nobody but safety may answer it (a forged answer would fake a decision).
    answering = {i for i in deployment.IDENTITIES if may(control, i, "declare_queryable", key)}
    assert answering == {"safety"}


def test_only_the_executor_asks_for_an_approval_and_the_agent_cannot_list_or_decide(
    control: dict[str, list[dict[str, object]]],
) -> None:
    request = keys.APPROVAL_REQUEST.key("r1")
    assert {i for i in deployment.IDENTITIES if may(control, i, "query", request)} == {"executor"}
    assert may(control, "operator", "query", keys.PENDING_PLANS.key("r1"))
    for service in (*OPERATOR_ONLY, keys.APPROVAL_REQUEST, keys.PENDING_PLANS):
        assert not may(control, "agent", "query", service.key("r1")), service.path
    # Another robot's operator has no say here.
    assert not may(control, "operator", "query", keys.SET_MODE.key("r2"))


def test_the_rules_are_what_this_test_reads() -> None:
    # The evaluator above, against a rule it must refuse and one it must allow.
    control = {
        "rules": [
            {"id": "a", "permission": "allow", "flows": ["ingress"], "messages": ["query"], "key_exprs": ["x/**"]}
        ],
        "policies": [{"id": "p", "rules": ["a"], "subjects": [deployment.username("r1", "operator")]}],
    }
    assert may(control, "operator", "query", "x/y")  # type: ignore[arg-type]
    assert not may(control, "operator", "put", "x/y")  # type: ignore[arg-type]
    assert not may(control, "agent", "query", "x/y")  # type: ignore[arg-type]


def test_no_agent_path_names_the_mode_or_the_approval_keys() -> None:
    # The MCP server, its robot API, the planner and the agent's tools may send plans, never decide on one.
    root = Path(__file__).resolve().parents[2]
    files = [root / "tether" / "agentapi.py", root / "tether" / "mcpserver.py", root / "tether" / "ask.py"]
    files += sorted((root / "services" / "planner").glob("*.py")) + sorted((root / "services" / "agent").glob("*.py"))
    names = (
        "SET_MODE",
        "APPROVAL_DECIDE",
        "ApprovalDecision",
        "ModeRequest",
        "safety/mode",
        "approval/decide",
        # Nor forget an incident or clear a caution zone.
        "FORGET_INCIDENT",
        "ForgetIncident",
        "incidents/forget",
    )
    for path in files:
        source = path.read_text()
        for name in names:
            assert name not in source, f"{path.relative_to(root)} names {name}"
