"""`tether deploy init`'s files: modes, certificates, rules scoped per robot, reruns that keep every secret."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID

from services.runtime import NodeSettings, zenoh_config_file
from tether import deployment
from tether.deployment import DeploymentError, RouterAddress


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def snapshot(directory: Path) -> dict[Path, bytes]:
    """Every file a rerun must keep: secrets, keys, certificates, client configs, the robots' config.
    (The router's config, its password list and the systemd/compose files are rewritten for every robot.)"""
    kept = [
        directory / "ca" / "ca.pem",
        directory / "ca" / "ca.key",
        directory / "router.key",
        directory / "router.pem",
    ]
    for home in (d for d in directory.iterdir() if (d / "tether.toml").exists()):
        kept += [home / n for n in ("ca.pem", "operator.token", "robot.key", "tether.toml")]
        kept += [home / f"{i}.{ext}" for i in deployment.IDENTITIES for ext in ("json5", "key", "pem")]
    return {p: p.read_bytes() for p in kept}


def common_name(path: Path) -> str:
    cert = x509.load_pem_x509_certificate(path.read_bytes())
    return str(cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value)


def acl(directory: Path) -> dict[str, object]:
    return json.loads(zenoh_config_file(directory / "router.json5").get_json("access_control"))


def test_every_secret_is_mode_600_and_every_identity_has_its_own_login(tmp_path: Path) -> None:
    written = deployment.init(tmp_path, ["r1"], tls=True)
    secrets_written = {w.path for w in written if w.secret}
    home = tmp_path / "r1"
    expected = {
        tmp_path / "router-users.txt",
        tmp_path / "ca" / "ca.key",
        tmp_path / "router.key",
        home / "operator.token",
        home / "robot.key",
        *(home / f"{i}.json5" for i in deployment.IDENTITIES),
        *(home / f"{i}.key" for i in deployment.IDENTITIES),
    }
    assert expected <= secrets_written
    for path in secrets_written:
        assert mode(path) == 0o600, path
    assert len(bytes.fromhex((home / "robot.key").read_text().strip())) == 32
    users = dict(line.split(":", 1) for line in (tmp_path / "router-users.txt").read_text().splitlines())
    assert set(users) == {f"r1-{i}" for i in deployment.IDENTITIES}
    assert len(set(users.values())) == len(users)
    for identity in deployment.IDENTITIES:
        conf = zenoh_config_file(home / f"{identity}.json5")
        auth = json.loads(conf.get_json("transport/auth/usrpwd"))
        assert (auth["user"], auth["password"]) == (f"r1-{identity}", users[f"r1-{identity}"])
        assert json.loads(conf.get_json("connect/endpoints")) == ["tls/localhost:7470"]
        assert common_name(home / f"{identity}.pem") == f"r1-{identity}"


def test_certificates_chain_to_the_ca_and_the_router_is_named_for_its_address(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"], tls=True, router=RouterAddress.parse("169.254.0.1:7999"))
    ca = x509.load_pem_x509_certificate((tmp_path / "ca" / "ca.pem").read_bytes())
    router = x509.load_pem_x509_certificate((tmp_path / "router.pem").read_bytes())
    router.verify_directly_issued_by(ca)
    sans = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(ip) for ip in sans.get_values_for_type(x509.IPAddress)] == ["169.254.0.1", "127.0.0.1"]
    assert sans.get_values_for_type(x509.DNSName) == ["localhost"]
    safety = x509.load_pem_x509_certificate((tmp_path / "r1" / "safety.pem").read_bytes())
    safety.verify_directly_issued_by(ca)
    assert (tmp_path / "r1" / "ca.pem").read_bytes() == (tmp_path / "ca" / "ca.pem").read_bytes()
    conf = zenoh_config_file(tmp_path / "r1" / "safety.json5")
    assert json.loads(conf.get_json("connect/endpoints")) == ["tls/169.254.0.1:7999"]
    assert json.loads(zenoh_config_file(tmp_path / "router.json5").get_json("listen/endpoints")) == ["tls/0.0.0.0:7999"]


def test_a_rerun_adds_a_robot_and_changes_no_secret_key_or_certificate(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"], tls=True)
    before = snapshot(tmp_path)
    users_before = set((tmp_path / "router-users.txt").read_text().splitlines())
    written = deployment.init(tmp_path, ["r2"], tls=True)
    after = snapshot(tmp_path)
    rewritten = {tmp_path / "router.json5", tmp_path / "router-users.txt", tmp_path / "deployment.json"}
    for path, data in before.items():
        if path not in rewritten:
            assert after[path] == data, f"{path} changed"
    assert users_before <= set((tmp_path / "router-users.txt").read_text().splitlines())
    assert (tmp_path / "r2" / "safety.json5").exists()
    assert all(not w.created for w in written if w.path in before and w.path not in rewritten)
    assert json.loads((tmp_path / "deployment.json").read_text())["robots"] == ["r1", "r2"]
    assert {"r1-safety", "r2-safety"} <= {s["id"] for s in acl(tmp_path)["subjects"]}  # type: ignore[index, union-attr]
    # Rerunning as it is changes nothing at all but the files that cover every robot.
    deployment.init(tmp_path, ["r1", "r2"], tls=True)
    again = snapshot(tmp_path)
    assert {p: d for p, d in again.items() if p not in rewritten} == {
        p: d for p, d in after.items() if p not in rewritten
    }
    assert set((tmp_path / "router-users.txt").read_text().splitlines()) >= users_before


def test_a_rerun_that_would_change_tls_or_the_router_is_refused(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"], router=RouterAddress.parse("edge:7480"))
    with pytest.raises(DeploymentError, match="without --tls"):
        deployment.init(tmp_path, ["r2"], tls=True)
    with pytest.raises(DeploymentError, match="edge:7480"):
        deployment.init(tmp_path, ["r2"], router=RouterAddress.parse("other"))
    deployment.init(tmp_path, ["r2"])  # the router it was made for is kept
    conf = zenoh_config_file(tmp_path / "r2" / "agent.json5")
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/edge:7480"]


@pytest.mark.parametrize("bad", ["", "r 1", "r1/x", "*", "r1**"])
def test_a_robot_name_that_would_widen_the_rules_is_refused(tmp_path: Path, bad: str) -> None:
    with pytest.raises(DeploymentError, match="robot name"):
        deployment.init(tmp_path, [bad])


@pytest.mark.parametrize(
    ("text", "host", "port"),
    [("localhost", "localhost", 7470), ("10.0.0.2:9000", "10.0.0.2", 9000), ("[::1]:7471", "::1", 7471)],
)
def test_router_addresses(text: str, host: str, port: int) -> None:
    assert RouterAddress.parse(text) == RouterAddress(host, port)


@pytest.mark.parametrize("text", ["host:port", "host:0", "a b", ":7470"])
def test_bad_router_addresses_are_named(text: str) -> None:
    with pytest.raises(DeploymentError, match="router address"):
        RouterAddress.parse(text)


def test_every_rule_is_scoped_to_its_robot_and_the_default_is_deny(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1", "r2"], tls=True)
    control = acl(tmp_path)
    assert control["enabled"] is True
    assert control["default_permission"] == "deny"
    for rule in control["rules"]:  # type: ignore[union-attr]
        robot = rule["id"].split("-")[0]
        assert all(k.startswith(f"tether/{robot}/") for k in rule["key_exprs"]), rule
    for subject in control["subjects"]:  # type: ignore[union-attr]
        assert subject["usernames"] == subject["cert_common_names"] == [subject["id"]]
    for policy in control["policies"]:  # type: ignore[union-attr]
        robot = policy["id"].split("-")[0]
        assert all(s.startswith(f"{robot}-") for s in policy["subjects"]), policy
    rights = {
        p["subjects"][0]: p["rules"]
        for p in control["policies"]  # type: ignore[union-attr]
        if p["id"] == "r1-own-agent"
    }
    assert rights == {"r1-agent": ["r1-alive-agent", "r1-trace-agent"]}


def test_the_agent_has_no_rule_to_command_reset_teleop_or_report_people(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"])
    control = acl(tmp_path)
    rules = {r["id"]: r for r in control["rules"]}  # type: ignore[union-attr]
    agent_rules = [
        rules[name]
        for p in control["policies"]  # type: ignore[union-attr]
        if "r1-agent" in p["subjects"]
        for name in p["rules"]
    ]
    ingress = [r for r in agent_rules if r["flows"] == ["ingress"]]
    writes = {
        k
        for r in ingress
        if set(r["messages"]) - {"declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"}
        for k in r["key_exprs"]
    }
    assert "tether/r1/safety/reset" not in writes
    assert not any(k.startswith(("tether/r1/cmd/", "tether/r1/world/humans")) for k in writes)
    robot_writes = {
        k
        for r in ingress
        if set(r["messages"]) - {"query", "declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"}
        for k in r["key_exprs"]
        if k.startswith("tether/r1/robot/")
    }
    assert robot_writes == set()


def test_relative_paths_in_a_zenoh_config_are_taken_from_its_directory(tmp_path: Path) -> None:
    (tmp_path / "creds").mkdir()
    path = tmp_path / "creds" / "client.json5"
    path.write_text(
        '{mode: "client", transport: {link: {tls: {root_ca_certificate: "ca.pem", connect_certificate: "/abs/c.pem",'
        ' connect_private_key: "sub/c.key"}}, auth: {usrpwd: {dictionary_file: "../users.txt"}}}}'
    )
    conf = NodeSettings(zenoh_config=path).zenoh("safety")
    tls = json.loads(conf.get_json("transport/link/tls"))
    assert tls["root_ca_certificate"] == str(tmp_path / "creds" / "ca.pem")
    assert tls["connect_private_key"] == str(tmp_path / "creds" / "sub" / "c.key")
    assert tls["connect_certificate"] == "/abs/c.pem"
    assert tls["listen_certificate"] is None
    usrpwd = json.loads(conf.get_json("transport/auth/usrpwd"))
    assert usrpwd["dictionary_file"] == str(tmp_path / "creds" / ".." / "users.txt")
    assert isinstance(conf, zenoh.Config)


def test_a_rerun_reports_as_written_only_what_changed(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"])
    again = deployment.init(tmp_path, ["r1"])
    assert [w.path for w in again if w.created] == []
    # Every generated file is reported, kept as it was.
    assert {tmp_path / "compose.yaml", tmp_path / "systemd" / "tether-r1-safety.service"} <= {w.path for w in again}
    added = {w.path: w.created for w in deployment.init(tmp_path, ["r2"])}
    assert added[tmp_path / "compose.yaml"] and added[tmp_path / "router.json5"]
    assert added[tmp_path / "systemd" / "tether-r2-safety.service"]
    assert not added[tmp_path / "systemd" / "tether-r1-safety.service"]
    assert not added[tmp_path / "r1" / "systemd.toml"]


def test_the_planners_api_key_file_is_secret_empty_and_kept(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"])
    key = tmp_path / "r1" / deployment.LLM_KEY_FILE
    assert mode(key) == 0o600 and key.read_text() == ""
    key.write_text("sk-installer\n")
    deployment.init(tmp_path, ["r1", "r2"])
    assert key.read_text() == "sk-installer\n"


@pytest.mark.parametrize(
    ("router", "tls", "warned"),
    [
        ("localhost", False, False),
        ("127.0.0.1:7471", False, False),
        ("[::1]", False, False),
        ("edge.lan", False, True),
        ("10.0.0.2", False, True),
        ("edge.lan", True, False),
    ],
)
def test_passwords_in_the_clear_across_a_network_are_warned_about(
    tmp_path: Path, router: str, tls: bool, warned: bool
) -> None:
    deployment.init(tmp_path, ["r1"], tls=tls, router=RouterAddress.parse(router))
    warning = deployment.cleartext_warning(deployment.Deployment.load(tmp_path))
    assert (warning is not None) == warned
    if warning is not None:
        assert "--tls" in warning and "in the clear" in warning


def test_deploy_init_prints_the_cleartext_warning(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from tether.cli import app

    result = CliRunner().invoke(app, ["deploy", "init", str(tmp_path / "d"), "--robot", "r1", "--router", "edge.lan"])
    assert result.exit_code == 0, result.output
    assert "warning:" in result.output and "in the clear" in result.output
    quiet = CliRunner().invoke(app, ["deploy", "init", str(tmp_path / "e"), "--robot", "r1"])
    assert quiet.exit_code == 0 and "warning:" not in quiet.output


def test_deploy_init_with_json_says_its_error_in_json(tmp_path: Path) -> None:
    """A script reading --json gets the refusal as one JSON object on stdout, not words on stderr."""
    from typer.testing import CliRunner

    from tether.cli import app

    result = CliRunner().invoke(app, ["deploy", "init", str(tmp_path / "d"), "--robot", "r/1", "--json"])
    assert result.exit_code == 2, result.output
    error = json.loads(result.stdout)["error"]
    assert "r/1" in error, error
    plain = CliRunner().invoke(app, ["deploy", "init", str(tmp_path / "d"), "--robot", "r/1"])
    assert plain.exit_code == 2 and not plain.stdout and "error:" in plain.stderr


def test_each_service_may_serve_only_its_own_keys(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"])
    control = acl(tmp_path)
    rules = {r["id"]: r for r in control["rules"]}  # type: ignore[union-attr]

    def served_by(identity: str) -> set[str]:
        return {
            k
            for p in control["policies"]  # type: ignore[union-attr]
            if f"r1-{identity}" in p["subjects"]
            for name in p["rules"]
            if "declare_queryable" in rules[name]["messages"] and rules[name]["flows"] == ["ingress"]
            for k in rules[name]["key_exprs"]
        }

    assert served_by("parser") == {"tether/r1/plan/parse", "tether/r1/_process/parser"}
    assert served_by("planner") == {"tether/r1/plan/ask", "tether/r1/plan/ask_cancel", "tether/r1/_process/planner"}
    assert "tether/r1/cmd/navigate_to_pose/_action/send_goal" in served_by("safety")
    assert "tether/r1/safety/reset" in served_by("safety")
    assert all(
        k.startswith(("tether/r1/cmd/", "tether/r1/safety/", "tether/r1/_process/")) for k in served_by("safety")
    )
    assert served_by("operator") == served_by("agent") == set()
    for identity in deployment.IDENTITIES:
        if identity != "safety":
            assert not any(k.startswith(("tether/r1/cmd/", "tether/r1/safety/")) for k in served_by(identity))
        # Each service answers `tether status` for its own process, and for no other's.
        process = {k for k in served_by(identity) if k.startswith("tether/r1/_process/")}
        assert process == ({f"tether/r1/_process/{identity}"} if identity in deployment.SERVICE_IDENTITIES else set())


def test_only_the_operator_forgets_incidents_those_who_ask_list_them_and_executor_and_robot_report(
    tmp_path: Path,
) -> None:
    deployment.init(tmp_path, ["r1"])
    control = acl(tmp_path)
    rules = {r["id"]: r for r in control["rules"]}  # type: ignore[union-attr]

    def may(identity: str, message: str) -> set[str]:
        return {
            k
            for p in control["policies"]  # type: ignore[union-attr]
            if f"r1-{identity}" in p["subjects"]
            for name in p["rules"]
            if message in rules[name]["messages"] and rules[name]["flows"] == ["ingress"]
            for k in rules[name]["key_exprs"]
        }

    forget, listing, report = (
        "tether/r1/safety/incidents/forget",
        "tether/r1/safety/incidents",
        "tether/r1/safety/incidents/report",
    )
    assert [i for i in deployment.IDENTITIES if forget in may(i, "query")] == ["operator"]
    # The planner and the agent before a plan (the caution zones), the operator with `tether incidents`.
    assert [i for i in deployment.IDENTITIES if listing in may(i, "query")] == ["planner", "operator", "agent"]
    reporters = [i for i in deployment.IDENTITIES if report in may(i, "put")]
    assert sorted(reporters) == ["executor", "ros2", "sim"]


def test_a_rerun_after_the_ca_was_replaced_issues_every_certificate_anew(tmp_path: Path) -> None:
    """Kept, the certificates the old CA signed were refused by a router and clients that trust the new one."""
    deployment.init(tmp_path, ["r1"], tls=True)
    before = snapshot(tmp_path)
    for name in ("ca.pem", "ca.key"):
        (tmp_path / "ca" / name).unlink()

    written = {w.path for w in deployment.init(tmp_path, ["r1"], tls=True) if w.created}

    ca = x509.load_pem_x509_certificate((tmp_path / "ca" / "ca.pem").read_bytes())
    certificates = [tmp_path / "router.pem", *(tmp_path / "r1" / f"{i}.pem" for i in deployment.IDENTITIES)]
    for path in certificates:
        x509.load_pem_x509_certificate(path.read_bytes()).verify_directly_issued_by(ca)
        assert path in written and path.with_suffix(".key") in written
        assert path.with_suffix(".key").read_bytes() != before[path.with_suffix(".key")], "a new key"
    assert (tmp_path / "r1" / "ca.pem").read_bytes() == (tmp_path / "ca" / "ca.pem").read_bytes()
    # The rest is kept: tokens, keys of the robot, client configs.
    for name in ("operator.token", "robot.key", "safety.json5", "tether.toml"):
        assert (tmp_path / "r1" / name).read_bytes() == before[tmp_path / "r1" / name]
    # And a certificate put back beside another key is issued anew too.
    safety = tmp_path / "r1" / "safety"
    safety.with_suffix(".key").write_bytes((tmp_path / "r1" / "planner.key").read_bytes())
    assert safety.with_suffix(".pem") in {w.path for w in deployment.init(tmp_path, ["r1"], tls=True) if w.created}
    again = deployment.init(tmp_path, ["r1"], tls=True)
    assert [w.path for w in again if w.created and w.path.suffix == ".pem"] == [], "kept once good"
