"""The TLS set-up of docs/security.md, end to end on loopback: certificates from
deploy/tls/make-certs.sh, the shipped deploy/tls/*.json5 configs (only their
/etc/tagswarm/tls paths pointed at the test's folder), mutual TLS plus user/password
plus the ACL on the router."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from tagswarm.deploy import acl, router
from tagswarm.protocol.bus import BusConfig, BusError, open_bus
from tagswarm.protocol.keys import Keys
from tests.harness import free_port

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")


def local_copy(name: str, certs: Path, folder: Path) -> str:
    """deploy/tls/``name`` with its certificate folder replaced by ``certs``."""
    text = (DEPLOY / "tls" / name).read_text()
    assert "/etc/tagswarm/tls/" in text
    out = folder / name
    out.write_text(text.replace("/etc/tagswarm/tls/", f"{certs}/"))
    return str(out)


def test_mutual_tls_with_passwords_and_acl(tmp_path: Path) -> None:
    certs = tmp_path / "tls"
    made = subprocess.run(["sh", str(DEPLOY / "tls" / "make-certs.sh"), str(certs), "localhost"],
                          capture_output=True, text=True, timeout=120)
    assert made.returncode == 0, made.stderr
    assert {"ca.pem", "router.pem", "router.key", "client.pem", "client.key"} <= {p.name for p in certs.iterdir()}
    secrets = tmp_path / "secrets"
    acl.make_secrets(secrets, acl.users((0, 1)))
    keys = Keys("tls")
    ep = f"tls/localhost:{free_port()}"
    args = router.parser().parse_args([
        "--listen", ep, "--run", keys.run, "--robots", "2", "--users", str(secrets / acl.USERS_FILE), "--acl",
        "--zenoh-config", local_copy("router-tls.json5", certs, tmp_path)])
    client_tls = local_copy("client-tls.json5", certs, tmp_path)

    def login(user: str, endpoint: str = ep, config: str | None = client_tls) -> BusConfig:
        return BusConfig(mode="client", connect=(endpoint,), user=user, config_file=config,
                         password_file=str(secrets / f"{user}{acl.PASSWORD_SUFFIX}"))

    with open_bus(router.router_config(args, {})), open_bus(login("viewer")) as viewer, \
            open_bus(login("world")) as world:
        ticks = viewer.subscribe(keys.tick())
        for _ in range(100):  # until the router knows the subscription
            world.put(keys.tick(), b"tick")
            if viewer.wait_for(lambda: len(ticks) > 0, 0.1):
                break
        assert [item.value for item in ticks.drain()][:1] == [b"tick"]
        # not trusting the CA, or plain TCP to a TLS-only router: no session
        for cfg in (login("viewer", config=None), login("viewer", ep.replace("tls/", "tcp/"))):
            with pytest.raises(BusError, match="cannot open Zenoh session"), open_bus(cfg):
                pass
