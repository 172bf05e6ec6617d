"""The ACL generator (tagswarm/deploy/acl.py), the router's security flags and the shipped
deploy/ files.  No session is opened; tests/integration/test_acl_sessions.py runs the rules."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest
import zenoh

from tagswarm.deploy import acl, router
from tagswarm.protocol.bus import key_matches
from tagswarm.protocol.keys import Keys

ROOT = Path(__file__).resolve().parents[3]
DEPLOY = ROOT / "deploy"
EXAMPLE = DEPLOY / "zenoh-router-acl.json5"
EXAMPLE_ARGV = ["--users", "/run/secrets/zenoh_users", "--acl", "--run", "compose", "--print-config"]
K = Keys("r")


def allowed(grant: tuple[str, ...], key: str) -> bool:
    return any(key_matches(p, key) for p in grant)


def test_agents_may_publish_only_their_own_robot_keys() -> None:
    g = acl.grants(K, (0, 1, 2))
    a1 = g["agent1"]
    for key in (K.observation(1), K.odometry(1), K.robot_status(1), K.cmd(1), K.ack("agent/1")):
        assert allowed(a1.put, key), key
    for key in (K.observation(2), K.correction(1), K.truth(1), K.image(1, "front"), K.encoders(1), K.map(),
                K.tick(), K.ack("agent/2"), K.ack("server/0"), K.goal(1), K.world_status()):
        assert not allowed(a1.put, key), key
    assert allowed(a1.sub, K.image(1, "front")) and not allowed(a1.sub, K.image(2, "front"))
    assert allowed(a1.sub, K.correction(1)) and not allowed(a1.sub, K.correction(0))
    assert not allowed(a1.sub, K.truth(1))  # agents never see the ground truth
    assert a1.token == (K.alive("agent/1"),)


def test_world_server_viewer_and_operator() -> None:
    g = acl.grants(K, (0, 1))
    assert allowed(g["world"].put, K.truth(1)) and allowed(g["world"].put, K.image(0, "rear"))
    assert allowed(g["world"].put, K.ack("render/3")) and not allowed(g["world"].put, K.ack("agent/0"))
    assert not allowed(g["world"].put, K.observation(0)) and not allowed(g["world"].put, K.correction(0))
    assert allowed(g["server"].put, K.correction(1)) and allowed(g["server"].put, K.map())
    assert not allowed(g["server"].put, K.observation(1)) and not allowed(g["server"].put, K.cmd(1))
    assert g["server"].serve == (K.map(),)
    # the server hears the agents' tick acks (an ack without its odometry: that odometry was lost), not the
    # render workers' or its own
    assert allowed(g["server"].sub, K.ack("agent/1")) and allowed(g["server"].sub, K.ack("agent/15"))
    assert not allowed(g["server"].sub, K.ack("render/0")) and not allowed(g["server"].sub, K.ack("server/0"))
    assert g["viewer"].put == () and g["viewer"].token == () and g["viewer"].serve == ()
    assert allowed(g["viewer"].sub, K.truth(1)) and allowed(g["viewer"].sub, K.image(1, "front"))
    assert g["operator"].put == (K.goal(), K.world_command())  # tagswarm goto, tagswarm kidnap
    assert allowed(g["world"].sub, K.world_command())
    assert not any(allowed(g[u].put, K.world_command()) for u in ("world", "server", "viewer", "agent0"))
    # nobody outside the run's own keys
    for grant in g.values():
        for field in ("put", "sub", "serve", "ask", "token", "watch", "discover"):
            for expr in getattr(grant, field):
                assert key_matches(K.all(), expr), expr


def test_the_access_control_block_denies_by_default_and_ties_each_user_to_its_rules() -> None:
    block = acl.access_control(K, (0, 1))
    assert block["enabled"] is True and block["default_permission"] == "deny"
    ids = [r["id"] for r in block["rules"]]
    assert len(ids) == len(set(ids))
    assert all(r["permission"] == "allow" and len(r["flows"]) == 1 and r["key_exprs"] for r in block["rules"])
    users = acl.users((0, 1))
    assert [s["id"] for s in block["subjects"]] == users
    assert [s["usernames"] for s in block["subjects"]] == [[u] for u in users]
    for policy in block["policies"]:
        assert policy["subjects"] == [policy["id"]]
        assert all(rid.startswith(f"{policy['id']}:") for rid in policy["rules"])
    viewer = {r["id"]: r for r in block["rules"] if r["id"].startswith("viewer:")}
    assert not any("put" in r["messages"] and r["flows"] == ["ingress"] for r in viewer.values())
    config = zenoh.Config()
    config.insert_json5("access_control", json.dumps(block))  # Zenoh accepts it


def test_the_shipped_example_is_what_the_generator_writes(capsys: pytest.CaptureFixture[str]) -> None:
    assert router.main(EXAMPLE_ARGV) == 0
    assert capsys.readouterr().out == EXAMPLE.read_text(), (
        f"deploy/ is stale: tagswarm router {' '.join(EXAMPLE_ARGV)} > {EXAMPLE.relative_to(ROOT)}")
    zenoh.Config.from_file(str(EXAMPLE))


@pytest.mark.parametrize("name", ["router-tls.json5", "client-tls.json5"])
def test_the_tls_examples_are_valid_zenoh_configs(name: str) -> None:
    zenoh.Config.from_file(str(DEPLOY / "tls" / name))


def test_make_secrets_writes_one_password_per_user_and_keeps_them(tmp_path: Path) -> None:
    folder = tmp_path / "s"
    users = acl.users((0, 1))
    written = acl.make_secrets(folder, users)
    assert len(written) == len(users) + 2
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    dictionary = dict(line.split(":", 1) for line in (folder / acl.USERS_FILE).read_text().splitlines())
    assert list(dictionary) == users
    for u in users:
        password = (folder / f"{u}{acl.PASSWORD_SUFFIX}").read_text().strip()
        assert dictionary[u] == password and len(password) >= 32 and ":" not in password
    assert len(set(dictionary.values())) == len(users)
    (folder / "agent0.password").write_text("chosen\n")
    again = acl.make_secrets(folder, acl.users((0, 1, 2)))  # one robot more
    assert [p.name for p in again] == ["agent2.password", acl.USERS_FILE, acl.AGENTS_FILE]
    dictionary2 = dict(line.split(":", 1) for line in (folder / acl.USERS_FILE).read_text().splitlines())
    assert dictionary2["agent0"] == "chosen" and dictionary2["world"] == dictionary["world"]
    # the claim authority's file: the agents' lines only
    agents = (folder / acl.AGENTS_FILE).read_text().splitlines()
    assert agents == [f"agent{r}:{dictionary2[f'agent{r}']}" for r in (0, 1, 2)]


def test_recorder_answers_claims_and_claimants_may_only_ask() -> None:
    g = acl.grants(K, (0, 1))
    claim = acl.claim_key(K)
    assert claim == "tagswarm/r/deploy/claim" and key_matches(K.all(), claim)
    rec, cl = g[acl.RECORDER], g[acl.CLAIMANT]
    assert rec.serve == (claim,) and rec.put == () and rec.token == (K.alive("recorder/0"),)
    assert allowed(rec.sub, K.truth(1)) and allowed(rec.sub, K.correction(0))
    assert cl.ask == (claim,) and cl.put == () and cl.sub == () and cl.serve == () and cl.token == ()
    assert allowed(cl.watch, K.alive("agent/1"))  # its container's healthcheck
    for user, grant in g.items():  # nobody else may answer a claim or ask for one
        if user not in (acl.RECORDER, acl.CLAIMANT):
            assert not allowed(grant.serve, claim) and not allowed(grant.ask, claim), user


@pytest.mark.parametrize("argv,message", [
    (["--acl"], "--acl needs --users"),
    (["--users", "/nonexistent/users.txt"], "--users: no such file"),
    (["--zenoh-user", "x"], "--zenoh-user and --zenoh-password-file go together"),
])
def test_router_security_mistakes_exit_2_with_one_line(argv: list[str], message: str,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    assert router.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"tagswarm router: error: {message}"), err


def test_client_credentials_from_flags_and_environment(tmp_path: Path) -> None:
    from tagswarm.world.config import build_config

    pw = tmp_path / "pw"
    pw.write_text("s3cret\n")
    c = build_config(["--zenoh-user", "world", "--zenoh-password-file", str(pw)], {})
    assert (c.bus.user, c.bus.password_file) == ("world", str(pw))
    assert "s3cret" not in repr(c)  # the config holds the file, never the password
    c = build_config([], {"TAGSWARM_ZENOH_USER": "agent0", "TAGSWARM_ZENOH_PASSWORD_FILE": str(pw)})
    assert (c.bus.user, c.bus.password_file) == ("agent0", str(pw))
    from tagswarm.runtime.config import ConfigError
    with pytest.raises(ConfigError, match="cannot read"):
        build_config(["--zenoh-user", "world", "--zenoh-password-file", str(tmp_path / "missing")], {})
    with pytest.raises(ConfigError, match="no ':'"):
        build_config(["--zenoh-user", "a:b", "--zenoh-password-file", str(pw)], {})
    # the router ignores a client's credentials from a compose-wide environment
    cfg = router.router_config(router.parser().parse_args([]), {"TAGSWARM_ZENOH_USER": "world",
                                                                "TAGSWARM_ZENOH_PASSWORD_FILE": str(pw)})
    assert cfg.user is None and cfg.password_file is None and cfg.users_file is None and cfg.access_control is None
