"""Read a live tagswarm run with nothing but ``zenoh`` and ``msgpack``: no tagswarm import.

Every sample is one msgpack map; its Zenoh encoding, ``application/msgpack;<MessageType>``,
names the message type (docs/protocol.md lists every key, type and field).  This prints,
per sample, the key, the type from the encoding and a few fields::

    tagswarm/demo/robot/1/odometry  OdometryEstimate  seq=412 stamp_ns=13733333333 robot_id=1 x_m=0.532 ...

Start a run that outside tools can join, then read it::

    tagswarm up --listen tcp/127.0.0.1:7447 --run demo
    python examples/raw_subscriber.py --connect tcp/127.0.0.1:7447 --run demo

With ``--schema docs/messages.schema.json`` (needs ``jsonschema``) every payload is also
validated against the JSON Schema of the msgpack form; ``--summary FILE`` writes per-key
counts, encodings, message types, QoS and validation results as JSON at the end.
Each key's first sample is announced on stderr (``new key <key> (<encoding>)``).
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time
from typing import Any

import msgpack
import zenoh

SHOWN = 5  # fields printed per sample besides the type


def _args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="raw_subscriber.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="Stops on Ctrl-C, or as --count / --duration / --idle-exit say.")
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447",
                    help="Zenoh endpoint of the run (tagswarm up --listen ...); default %(default)s")
    ap.add_argument("--run", default="*", help="run id (tagswarm up --run ...); default: every run")
    ap.add_argument("--key", default=None, help="key expression to read instead of tagswarm/<run>/**")
    ap.add_argument("--count", type=int, default=0, help="stop after this many samples (0: no limit)")
    ap.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: no limit)")
    ap.add_argument("--idle-exit", type=float, default=0.0, metavar="S",
                    help="stop when nothing arrived for S seconds after the first sample (the run ended)")
    ap.add_argument("--schema", default=None, help="validate every payload against this JSON Schema file")
    ap.add_argument("--summary", default=None, help="write a JSON summary of what was read to this file")
    ap.add_argument("--quiet", action="store_true", help="print nothing per sample")
    args = ap.parse_args(argv)
    if args.count < 0 or args.duration < 0 or args.idle_exit < 0:
        ap.error("--count, --duration and --idle-exit must not be negative")
    return args


def _validators(path: str) -> tuple[dict[str, Any], dict[str, str]]:
    """One validator per message type of the schema file, and each type's ``type`` tag."""
    import jsonschema

    with open(path, encoding="utf-8") as fh:
        schema = json.load(fh)
    checker = jsonschema.FormatChecker()
    checker.checks("binary")(lambda value: isinstance(value, bytes))  # msgpack bin: raw bytes
    validators, tags = {}, {}
    for name, definition in schema["$defs"].items():
        one = {"$schema": schema.get("$schema"), "$defs": schema["$defs"], "$ref": f"#/$defs/{name}"}
        validators[name] = jsonschema.Draft202012Validator(one, format_checker=checker)
        tag = definition.get("properties", {}).get("type", {}).get("enum", [None])[0]
        if tag is not None:
            tags[name] = tag
    return validators, tags


def _short(value: Any) -> str:
    if isinstance(value, bytes):
        return f"<{len(value)} bytes>"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, dict)):
        text = json.dumps(value, default=lambda b: f"<{len(b)} bytes>")
        return text if len(text) <= 40 else text[:37] + "..."
    return str(value)


def main(argv: list[str] | None = None) -> int:
    args = _args(argv)
    key = args.key or f"tagswarm/{args.run}/**"
    validators, tags = _validators(args.schema) if args.schema else ({}, {})
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    inbox: queue.Queue[tuple[str, str, bytes, str, bool]] = queue.Queue()

    def on_sample(sample: zenoh.Sample) -> None:  # Zenoh's thread: copy and enqueue, nothing else
        inbox.put((str(sample.key_expr), str(sample.encoding), sample.payload.to_bytes(),
                   str(sample.congestion_control), bool(sample.express)))

    per_key: dict[str, dict[str, Any]] = {}
    total, start, last = 0, time.monotonic(), None
    with zenoh.open(conf) as session:
        session.declare_subscriber(key, on_sample)
        print(f"reading {key} from {args.connect}", file=sys.stderr, flush=True)
        try:
            while True:
                now = time.monotonic()
                if args.duration and now - start >= args.duration:
                    break
                if args.idle_exit and last is not None and now - last >= args.idle_exit:
                    break
                try:
                    got = inbox.get(timeout=0.1)
                except queue.Empty:
                    continue
                if got[0] not in per_key:
                    print(f"new key {got[0]} ({got[1]})", file=sys.stderr, flush=True)
                last, total = time.monotonic(), total + 1
                _handle(*got, per_key=per_key, validators=validators, tags=tags, quiet=args.quiet)
                if args.count and total >= args.count:
                    break
        except KeyboardInterrupt:
            pass
    if args.summary:
        summary = {"key_expr": key, "samples": total, "keys": per_key,
                   "tagswarm_imported": any(name.split(".")[0] == "tagswarm" for name in sys.modules)}
        with open(args.summary, "w", encoding="utf-8") as fh:
            json.dump(summary, fh, indent=2, sort_keys=True, default=sorted)
    return 0


def _handle(key: str, encoding: str, payload: bytes, congestion: str, express: bool, *, per_key: dict[str, Any],
            validators: dict[str, Any], tags: dict[str, str], quiet: bool) -> None:
    """Decode one sample, note what it was, print a line."""
    media, _, type_name = encoding.partition(";")
    row = per_key.setdefault(key, {"count": 0, "encodings": set(), "tags": set(), "qos": set(), "invalid": 0,
                                   "errors": [], "tag_mismatch": 0})
    row["count"] += 1
    row["encodings"].add(encoding)
    row["qos"].add(f"{congestion}{' express' if express else ''}")
    try:
        msg = msgpack.unpackb(payload, raw=False)
    except Exception as exc:  # not msgpack at all
        row["invalid"] += 1
        row["errors"] = (row["errors"] + [f"not msgpack: {exc}"])[:3]
        return
    tag = msg.get("type") if isinstance(msg, dict) else None
    row["tags"].add(str(tag))
    if tags and tags.get(type_name) != tag:
        row["tag_mismatch"] += 1
    if validators:
        validator = validators.get(type_name)
        problems = ([f"no schema for encoding {encoding!r}"] if validator is None
                    else [f"{list(e.absolute_path)}: {e.message}" for e in validator.iter_errors(msg)])
        if problems:
            row["invalid"] += 1
            row["errors"] = (row["errors"] + problems)[:3]
    if not quiet and isinstance(msg, dict):
        fields = " ".join(f"{k}={_short(v)}" for k, v in list(msg.items())[1 : 1 + SHOWN])
        print(f"{key}  {type_name or media or '?'}  {fields}", flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
