"""Cost of a publication on the hot path: ``Bus.put`` of a small message (EncoderTicks,
BLOCK) and of a camera frame (320x240 CameraImage, DROP), against the bare zenoh
publisher with and without an explicit encoding; ``--baseline FILE`` also times the
``Bus`` of another ``bus.py`` (e.g. ``git show HEAD~1:protocol/bus.py > /tmp/bus.py``)
in the same conditions, interleaved.  Three settings: ``python_side`` (``Publisher.put``
over a publisher that sends nothing: the cost of choosing the encoding), ``isolated`` (a
Zenoh session without subscribers) and ``loopback`` (a subscriber in a second session over loopback TCP:
what a put costs in a run, noisy on a loaded machine).  Writes
``bench/results/wire_encoding.json`` under ``--label``.

Usage: python bench/wire_encoding.py [--n 20000] [--repeat 7] [--baseline /tmp/bus.py] [--label current]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path
from types import ModuleType
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402

from tagswarm.protocol import bus as bus_module  # noqa: E402
from tagswarm.protocol import codec  # noqa: E402
from tagswarm.protocol import messages as m  # noqa: E402
from tagswarm.protocol.bus import BusConfig, open_bus  # noqa: E402
from tagswarm.protocol.keys import Keys  # noqa: E402
from tests.harness import endpoint  # noqa: E402

OUT = ROOT / "bench" / "results" / "wire_encoding.json"


def _messages() -> dict[str, tuple[str, bytes, bool]]:
    k = Keys("bench")
    enc = m.EncoderTicks(seq=1, stamp_ns=33_333_333, robot_id=1, left_ticks=1234, right_ticks=1250, ticks_per_rev=4096)
    img = m.CameraImage(seq=1, stamp_ns=0, robot_id=1, camera="front", step=0, width=320, height=240, fx_px=300.0,
                        fy_px=300.0, cx_px=159.5, cy_px=119.5, mount=m.Pose3(x_m=0.1, y_m=0.0, z_m=0.2),
                        data=bytes(320 * 240))
    return {"encoders": (k.encoders(1), codec.encode(enc), False), "image_320x240": (k.image(1, "front"),
                                                                                     codec.encode(img), True)}


def _per_put_us(fn: Callable[[], None], n: int) -> float:
    """Mean wall time of one call over ``n`` calls, in microseconds."""
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n * 1e6


def _load_bus(path: str | None) -> ModuleType:
    if path is None:
        return bus_module
    spec = importlib.util.spec_from_file_location("tagswarm.protocol._bench_baseline_bus", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _measure(ep: str | None, n: int, repeat: int, baseline: ModuleType | None) -> dict[str, dict[str, float]]:
    """Per message: microseconds per put of the current Bus, the baseline's, the bare zenoh publisher."""
    conf = BusConfig(listen=(ep,)) if ep else BusConfig()
    results: dict[str, dict[str, float]] = {}
    with open_bus(conf) as bus, (zenoh.open(_client_conf(ep)) if ep else nullcontext()) as sub_session:
        if sub_session is not None:
            sub_session.declare_subscriber("tagswarm/bench/**", lambda _s: None)
            time.sleep(1.0)  # let the subscription propagate before timing (a bench, not a test)
        old = None if baseline is None else baseline.Bus(bus._session)
        enc = zenoh.Encoding("application/msgpack;Bench")
        for name, (key, payload, drop) in _messages().items():
            count = n if not drop else max(n // 10, 100)
            cc = zenoh.CongestionControl.DROP if drop else zenoh.CongestionControl.BLOCK
            raw = bus._session.declare_publisher(key + "/raw", congestion_control=cc, express=not drop)
            bus.put(key, payload, drop=drop)  # declare the cached publishers outside the timing
            if old is not None:
                old.put(key + "/old", payload, drop=drop)
            r: dict[str, float] = {"payload_bytes": len(payload)}
            for _ in range(repeat):  # interleaved, so load changes hit every variant alike
                _add(r, "bus_put_us", _per_put_us(lambda k=key, p=payload, d=drop: bus.put(k, p, drop=d), count))
                if old is not None:
                    _add(r, "baseline_bus_put_us",
                         _per_put_us(lambda k=key + "/old", p=payload, d=drop: old.put(k, p, drop=d), count))
                _add(r, "zenoh_put_us", _per_put_us(lambda r=raw, p=payload: r.put(p), count))
                _add(r, "zenoh_put_with_encoding_us",
                     _per_put_us(lambda r=raw, p=payload: r.put(p, encoding=enc), count))
            results[name] = {k: statistics.median(v) if isinstance(v, list) else v for k, v in r.items()}
            raw.undeclare()
    return results


class _NopPublisher:
    def put(self, payload: bytes, *, encoding: Any = None) -> None:
        pass


def _python_side(n: int, repeat: int, baseline: ModuleType | None) -> dict[str, dict[str, float]]:
    """What ``Publisher.put`` itself costs (a publisher that sends nothing): the price of
    choosing the encoding, without Zenoh's noise."""
    results: dict[str, dict[str, float]] = {}
    for name, (_, payload, _) in _messages().items():
        new = bus_module.Publisher(lambda _enc: _NopPublisher())
        new.put(payload)
        old = None if baseline is None else baseline.Publisher(_NopPublisher())
        r: dict[str, Any] = {}
        for _ in range(repeat):
            _add(r, "publisher_put_us", _per_put_us(lambda p=payload, pub=new: pub.put(p), n * 10))
            if old is not None:
                _add(r, "baseline_publisher_put_us", _per_put_us(lambda p=payload, pub=old: pub.put(p), n * 10))
        results[name] = {k: statistics.median(v) for k, v in r.items()}
    return results


def _add(r: dict[str, Any], name: str, value: float) -> None:
    r.setdefault(name, []).append(value)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--n", type=int, default=20000, help="puts per timed loop (images: n/10)")
    ap.add_argument("--repeat", type=int, default=7, help="timed loops per variant; the median is reported")
    ap.add_argument("--baseline", default=None, help="another bus.py to time alongside (the version before a change)")
    ap.add_argument("--label", default="current", help="name of this measurement in the JSON file")
    args = ap.parse_args(argv)
    baseline = None if args.baseline is None else _load_bus(args.baseline)
    settings = {"python_side": _python_side(args.n, args.repeat, baseline),
                "isolated": _measure(None, args.n, args.repeat, baseline),
                "loopback": _measure(endpoint(), args.n, args.repeat, baseline)}
    doc = json.loads(OUT.read_text()) if OUT.exists() else {}
    doc[args.label] = {"settings": settings, "n": args.n, "repeat": args.repeat, "baseline": args.baseline,
                       "machine": platform.node(), "cpus": os.cpu_count(), "load_avg_1m": os.getloadavg()[0],
                       "python": platform.python_version(), "zenoh": getattr(zenoh, "__version__", "?")}
    OUT.write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    for setting, results in settings.items():
        for name, r in results.items():
            print(f"{setting} {name}: " + ", ".join(f"{k} {v:.2f}" for k, v in r.items()))
    return 0


def _client_conf(ep: str) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([ep]))
    return conf


if __name__ == "__main__":
    raise SystemExit(main())
