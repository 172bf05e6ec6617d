"""A live lockstep run read by plain zenoh + msgpack: ``examples/raw_subscriber.py`` in its
own process (no tagswarm import, checked) reads a short paper run (3 robots, a render
worker, a goal and a push sent by the operator tools) and every key's samples carry the
Zenoh encoding of the message type docs/protocol.md gives that key, every message type
of the run arrives, and every payload validates against docs/messages.schema.json."""

from __future__ import annotations

import csv
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tagswarm.protocol import codec, wire
from tagswarm.protocol import messages as m
from tagswarm.protocol.keys import Keys
from tests.harness import client, endpoint, script, stop, wait_alive

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "raw_subscriber.py"
SCHEMA = ROOT / "docs" / "messages.schema.json"
ROBOTS = 3
PUSHED = 2


def _port_open(ep: str) -> bool:
    host, port = ep.removeprefix("tcp/").rsplit(":", 1)
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex((host, int(port))) == 0


def _wait_for(what: str, check: object, timeout_s: float, *procs: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():  # type: ignore[operator]
        for p in procs:
            assert p.poll() is None, f"{p.args[:2]} exited with {p.returncode} while waiting for {what}"
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)


@pytest.fixture
def raw_run(tmp_path: Path) -> Iterator[tuple[dict, Path, Keys]]:
    """Run the swarm and the raw reader; yield the reader's summary, the run folder, the keys."""
    ep, run = endpoint(), f"raw{os.getpid()}"
    keys, out, summary = Keys(run), tmp_path / "run", tmp_path / "summary.json"
    env = {k: v for k, v in os.environ.items() if not k.startswith("TAGSWARM_")}
    with open(tmp_path / "up.log", "wb") as up_log, open(tmp_path / "reader.log", "wb") as reader_log:
        up = subprocess.Popen([script("tagswarm"), "up", "--scenario", "paper", "--clock", "lockstep",
                               "--duration", "12", "--robots", str(ROBOTS), "--set", "render.workers=1",
                               "--listen", ep, "--run", run, "--out", str(out), "--no-live", "--no-report"],
                              stdout=up_log, stderr=subprocess.STDOUT, env=env)
        reader: subprocess.Popen[bytes] | None = None
        try:
            _wait_for("the world to listen", lambda: _port_open(ep), 60, up)
            # outside the repository, with a plain interpreter: only zenoh, msgpack, jsonschema
            reader = subprocess.Popen([sys.executable, str(EXAMPLE), "--connect", ep, "--run", run, "--quiet",
                                       "--schema", str(SCHEMA), "--summary", str(summary), "--idle-exit", "8"],
                                      stdout=reader_log, stderr=subprocess.STDOUT, cwd=tmp_path,
                                      env={k: v for k, v in env.items() if k != "PYTHONPATH"})
            log = tmp_path / "reader.log"
            _wait_for("the reader's first sample", lambda: b"new key" in log.read_bytes(), 60, up, reader)
            with client(ep) as bus:
                for rid in range(ROBOTS):
                    wait_alive(bus, keys, f"agent/{rid}", timeout_s=60)
                common = ["--connect", ep, "--run", run, "--timeout", "60"]
                ops = [subprocess.run([script("tagswarm"), "goto", "1", "0.5", "0.5", *common], env=env,
                                      capture_output=True, timeout=120),
                       subprocess.run([script("tagswarm"), "kidnap", str(PUSHED), "0.0", "0.8", "--push", *common],
                                      env=env, capture_output=True, timeout=120)]
                for op in ops:
                    assert op.returncode == 0, op.stderr.decode()
                # A CLI publishes right after joining and leaves: its one sample can miss a peer whose
                # subscription it has not heard of yet (the world got it: the push happened).  Until the
                # reader has each key, the same kind of message again from this long-joined session:
                # the goal repeated, a push by nothing.
                again = {keys.goal(1): m.Goal(seq=1, stamp_ns=0, robot_id=1, x_m=0.5, y_m=0.5),
                         keys.world_command(): m.WorldCommand(seq=1, stamp_ns=0, robot_id=PUSHED, action="push",
                                                              x_m=0.0, y_m=0.0)}
                for key, msg in again.items():
                    deadline = time.monotonic() + 30
                    while f"new key {key} ".encode() not in log.read_bytes():
                        assert time.monotonic() < deadline and up.poll() is None, f"the reader never got {key}"
                        bus.put(key, codec.encode(msg))
                        bus.wait_for(lambda k=key: f"new key {k} ".encode() in log.read_bytes(), 1.0)
            up.wait(timeout=600)
            assert up.returncode == 0, (tmp_path / "up.log").read_text()[-3000:]
            reader.wait(timeout=120)
            assert reader.returncode == 0, log.read_text()[-3000:]
        finally:
            stop(up)
            if reader is not None:
                stop(reader)
    yield json.loads(summary.read_text()), out, keys


def test_a_plain_zenoh_msgpack_reader_sees_every_type_encoded_and_schema_valid(
        raw_run: tuple[dict, Path, Keys]) -> None:
    summary, out, keys = raw_run
    assert summary["tagswarm_imported"] is False
    rows: dict[str, dict] = summary["keys"]
    assert summary["samples"] > 1000 and rows
    seen: set[type[m.Msg]] = set()
    for key, row in rows.items():
        spec = wire.spec_for_key(keys, key)
        assert spec is not None and spec.message is not None, f"{key} is not in docs/protocol.md"
        # every sample of the key carries the encoding of the type the docs give it, and says so in `type`
        assert row["encodings"] == [wire.encoding_of(spec.message)], (key, row["encodings"])
        assert row["tags"] == [spec.message.__struct_config__.tag] and row["tag_mismatch"] == 0, (key, row)
        assert row["invalid"] == 0, (key, row["errors"])
        # lockstep: nothing may be lost, so every key (camera images too) is BLOCK, express
        assert row["qos"] == ["CongestionControl.BLOCK express"], (key, row["qos"])
        seen.add(spec.message)
    with open(out / "relocalisations.csv", newline="") as fh:
        relocalised = any(csv.DictReader(fh))
    # a claim reply answers a compose agent container's query: tests/e2e/test_compose_containers.py
    expected = set(wire.MESSAGE_TYPES) - {m.ClaimReply} - (set() if relocalised else {m.Relocalisation})
    assert seen >= expected, f"never seen: {sorted(c.__name__ for c in expected - seen)}"
    robots = {keys.robot_id_of(k) for k in rows if keys.robot_id_of(k) is not None}
    assert robots == set(range(ROBOTS))
    assert rows[keys.goal(1)]["count"] >= 1 and rows[keys.world_command()]["count"] >= 1
