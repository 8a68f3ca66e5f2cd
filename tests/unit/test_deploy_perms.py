"""`tether deploy init` keeps its secrets its owner's whatever the umask, and says clearly what it cannot use."""

from __future__ import annotations

import datetime as dt
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from tether import deployment, deployunits
from tether.deployment import DeploymentError

# Every directory deploy init makes inside its own, for robot r1 with --tls.
OWN_DIRS = ("", "ca", "r1", "r1/state", "systemd", "compose")


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.fixture
def umask(request: pytest.FixtureRequest) -> Iterator[int]:
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


@pytest.mark.parametrize("umask", [0o000, 0o002, 0o022], indirect=True)
def test_a_permissive_umask_leaves_nothing_open_to_others(tmp_path: Path, umask: int) -> None:
    """Under umask 0 every directory came out 777: anyone could swap the CA's key, a certificate or a unit."""
    directory = tmp_path / "made" / "for" / "fleet"
    written = deployment.init(directory, ["r1"], tls=True)
    for name in OWN_DIRS:
        assert mode(directory / name) == 0o700, name
    for parent in (tmp_path / "made", tmp_path / "made" / "for"):  # made on the way: nobody else writes in them
        assert mode(parent) == 0o755, parent
    for w in written:
        assert mode(w.path) == (0o600 if w.secret else 0o644), w.path


def test_a_rerun_closes_what_an_earlier_run_or_a_copy_left_open(tmp_path: Path) -> None:
    """A deployment made by an earlier tether (or loosened by a copy) is set right; no secret changes."""
    written = deployment.init(tmp_path, ["r1"], tls=True)
    secrets = [w.path for w in written if w.secret]
    before = {p: p.read_bytes() for p in secrets}
    for name in OWN_DIRS[1:]:
        (tmp_path / name).chmod(0o777)
    for path in secrets:
        path.chmod(0o644)
    again = deployment.init(tmp_path, ["r1"], tls=True)
    assert not any(w.created for w in again if w.secret)
    assert {p: p.read_bytes() for p in secrets} == before
    for name in OWN_DIRS[1:]:
        assert mode(tmp_path / name) == 0o700, name
    for path in secrets:
        assert mode(path) == 0o600, path


def test_a_directory_others_may_write_in_is_refused_and_left_as_it_was(tmp_path: Path) -> None:
    """The directory named may be a shared one (/tmp): never changed, nothing written in it."""
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)
    with pytest.raises(DeploymentError, match=r"others may write in .*shared \(mode 1777\)"):
        deployment.init(shared, ["r1"])
    assert mode(shared) == 0o1777 and not any(shared.iterdir())
    # Readable by others but written only by its owner (a `mkdir /etc/tether`): used, and left as it was.
    readable = tmp_path / "etc-tether"
    readable.mkdir(mode=0o755)
    readable.chmod(0o755)
    deployment.init(readable, ["r1"])
    assert mode(readable) == 0o755 and mode(readable / "r1") == 0o700


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a directory to another user needs root")
def test_a_directory_of_another_user_is_refused(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"])
    os.chown(tmp_path / "r1", 12345, 12345)
    with pytest.raises(DeploymentError, match=r"r1 belongs to uid 12345, not to you"):
        deployment.init(tmp_path, ["r1"])
    assert (tmp_path / "r1").stat().st_uid == 12345


@pytest.mark.parametrize("robot", ["robøt", "r²", "ロボット"])
def test_a_robot_name_systemd_and_compose_cannot_take_is_refused(tmp_path: Path, robot: str) -> None:
    """Non-ASCII letters passed, and named units systemd refuses (`Failed to prepare filename`)."""
    with pytest.raises(DeploymentError, match="ASCII letters"):
        deployment.init(tmp_path, [robot])
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("robot", ["ca", "systemd", "compose"])
def test_a_robot_name_of_the_deployments_own_directory_is_refused(tmp_path: Path, robot: str) -> None:
    """Robot `ca`'s files, which go to its hosts, were written beside the CA's key; `systemd`'s among the units."""
    with pytest.raises(DeploymentError, match=f"taken by the deployment's own {robot}/ directory"):
        deployment.init(tmp_path, [robot], tls=True)
    assert not any(tmp_path.iterdir())


def make_ca(directory: Path, *, valid_until: dt.datetime) -> None:
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "an old CA")])
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(valid_until - dt.timedelta(days=30))
        .not_valid_after(valid_until)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .sign(key, hashes.SHA256())
    )
    pkcs8, none = serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    (directory / "ca.key").write_bytes(key.private_bytes(serialization.Encoding.PEM, pkcs8, none))
    (directory / "ca.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def test_a_damaged_ca_key_is_a_clear_error(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"], tls=True)
    (tmp_path / "ca" / "ca.key").write_text("not a key\n")
    with pytest.raises(DeploymentError, match=r"the CA in .*ca is unreadable or damaged.*delete .*ca and rerun"):
        deployment.init(tmp_path, ["r1"], tls=True)


def test_a_ca_key_of_another_ca_is_refused(tmp_path: Path) -> None:
    """It signed certificates naming a CA that did not sign them: every run issued them all anew, all refused."""
    deployment.init(tmp_path / "one", ["r1"], tls=True)
    deployment.init(tmp_path / "other", ["r1"], tls=True)
    (tmp_path / "one" / "ca" / "ca.key").write_bytes((tmp_path / "other" / "ca" / "ca.key").read_bytes())
    certificate = (tmp_path / "one" / "r1" / "safety.pem").read_bytes()
    with pytest.raises(DeploymentError, match=r"ca\.key is not the key of .*ca\.pem"):
        deployment.init(tmp_path / "one", ["r1"], tls=True)
    assert (tmp_path / "one" / "r1" / "safety.pem").read_bytes() == certificate


def test_an_expired_ca_is_a_clear_error(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"])  # without the CA, made next by hand
    (tmp_path / "ca").mkdir(mode=0o700)
    make_ca(tmp_path / "ca", valid_until=dt.datetime.now(dt.UTC) - dt.timedelta(days=1))
    manifest = tmp_path / deployment.MANIFEST
    manifest.write_text(manifest.read_text().replace('"tls": false', '"tls": true'))
    with pytest.raises(DeploymentError, match=r"the CA in .*ca expired on \d{4}-\d\d-\d\d"):
        deployment.init(tmp_path, ["r1"], tls=True)


@pytest.mark.parametrize(
    ("text", "says"),
    [
        (b"[safety\n", "is not valid TOML"),
        (b"[safety]\n\xff = 1\n", "is not valid TOML"),
        # Valid TOML, but not in the layout whose paths it sets line by line.
        (b'safety.operator_token_file = "/x"\n', "cannot set this host's paths in"),
    ],
)
def test_a_tether_toml_it_cannot_use_is_a_clear_error(tmp_path: Path, text: bytes, says: str) -> None:
    deployment.init(tmp_path, ["r1"])
    (tmp_path / "r1" / "tether.toml").write_bytes(text)
    with pytest.raises(DeploymentError, match=says) as refused:
        deployment.init(tmp_path, ["r1"])
    assert str(tmp_path / "r1" / "tether.toml") in str(refused.value)
    with pytest.raises(DeploymentError, match=says):
        deployunits.write_all(tmp_path, ["r1"], tls=False)


def test_a_password_list_that_is_not_text_is_a_clear_error(tmp_path: Path) -> None:
    deployment.init(tmp_path, ["r1"])
    with open(tmp_path / deployment.USERS_FILE, "ab") as f:
        f.write(b"\xff\xfe:x\n")
    with pytest.raises(DeploymentError, match=r"router-users\.txt is not text"):
        deployment.init(tmp_path, ["r1"])


def test_a_directory_whose_path_is_not_utf8_is_refused(tmp_path: Path) -> None:
    """Its tether.toml names its files by absolute path, which TOML cannot hold: it was written anyway,
    a config no service could load."""
    odd = Path(os.fsdecode(bytes(tmp_path) + b"/fleet-\xff"))
    with pytest.raises(DeploymentError, match="is not a UTF-8 path"):
        deployment.init(odd, ["r1"])
    assert not odd.exists()
