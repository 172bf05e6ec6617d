"""The pure part of ``tagswarm record``: received payloads in, an MCAP file out.

:class:`McapRecording` keeps the MCAP bookkeeping: one raw channel per key (payload bytes
exactly as received), Foxglove views beside them, optional image downsampling
(:func:`scale_image`), counters per message type and per reject kind, and the frames a
tick promised but that never arrived.  No Zenoh here: :mod:`tagswarm.recording.record` feeds it
from the bus (and ``bench/record.py`` and the tests feed it directly).
:func:`with_recorder` / :func:`without_recorders` add or strip the recorder as a
lockstep participant of a scenario.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from pathlib import Path
from typing import Final, Literal

import cv2
import msgspec
import numpy as np

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.layout import arena_to_map
from tagswarm.protocol.scenario import Scenario
from tagswarm.recording.foxglove_views import FoxgloveViews
from tagswarm.recording.mcapio import META_RUN, META_STATS, McapSink
from tagswarm.runtime import streams
from tagswarm.runtime.config import ConfigError

RECORDER_NAME: Final = "tagswarm record"  # the tool named in a recording's metadata
RECORD_PARTICIPANT: Final = "record/0"
log = logging.getLogger("tagswarm.record")  # the recorder's logger, whichever module logs


class RecordOptions(msgspec.Struct, frozen=True, kw_only=True):
    """What to write besides the raw payloads."""

    images: bool = True
    image_scale: float = 1.0
    foxglove: bool = True
    compression: Literal["zstd", "lz4", "none"] = "zstd"


def with_recorder(scenario: Scenario, participant: str = RECORD_PARTICIPANT) -> Scenario:
    """``scenario`` with ``participant`` added to a lockstep run's participants (unchanged
    in realtime, where the world waits for nobody)."""
    c = scenario.clock
    if c.mode != "lockstep" or participant in c.participants:
        return scenario
    return msgspec.structs.replace(scenario, clock=msgspec.structs.replace(c, participants=(*c.participants,
                                                                                              participant)))


def without_recorders(scenario: Scenario) -> Scenario:
    """``scenario`` without ``record/*`` participants and without observers: the run as it
    is to be reproduced (a replay must not wait for the original run's recorder or ``up``)."""
    c = scenario.clock
    kept = tuple(p for p in c.participants if not p.startswith("record/"))
    return msgspec.structs.replace(scenario, clock=msgspec.structs.replace(c, participants=kept, observers=()))


def scale_image(img: m.CameraImage, scale: float) -> m.CameraImage:
    """``img`` resized by ``scale`` (0 < scale <= 1) with area averaging; intrinsics follow
    (OpenCV pixel-centre convention: c' = (c + 0.5) * s - 0.5)."""
    w, h = max(1, round(img.width * scale)), max(1, round(img.height * scale))
    if (w, h) == (img.width, img.height):
        return img
    gray = np.frombuffer(img.data, np.uint8).reshape(img.height, img.width)
    small = cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA)
    sx, sy = w / img.width, h / img.height
    return msgspec.structs.replace(img, width=w, height=h, fx_px=img.fx_px * sx, fy_px=img.fy_px * sy,
                                   cx_px=(img.cx_px + 0.5) * sx - 0.5, cy_px=(img.cy_px + 0.5) * sy - 0.5,
                                   data=small.tobytes())


class McapRecording:
    """The pure part of a recorder: payloads in (key, bytes, wall time of reception),
    MCAP out.  Never raises on bad payloads: they are written raw and counted."""

    def __init__(self, path: Path, options: RecordOptions, *, run: str, keyexpr: str,
                 scenario: Scenario | None = None) -> None:
        if not (0 < options.image_scale <= 1) or not math.isfinite(options.image_scale):
            raise ConfigError("--image-scale must be in (0, 1]")
        self.options = options
        self.sink = McapSink(path, compression=options.compression)
        views = None
        if options.foxglove:
            a2m = arena_to_map(scenario) if scenario is not None else None
            views = FoxgloveViews(a2m, scenario.robot.cube_edge_m if scenario is not None else 0.2)
        self.views = views
        self.rejects = streams.RejectCounter(log)
        self.kinds: Counter[str] = Counter()  # messages written per tagswarm type
        self.skipped_images = 0
        # (robot_id/camera, step) promised by ticks vs received: a lossy recording says so in its stats
        self._frames_promised: set[tuple[str, int]] = set()
        self._frames_seen: set[tuple[str, int]] = set()
        self.first_ns: int | None = None
        self.last_ns = 0
        meta = {"run": run, "keyexpr": keyexpr, "images": str(options.images).lower(),
                "image_scale": repr(options.image_scale), "foxglove": str(options.foxglove).lower(),
                "recorder": RECORDER_NAME, "started_wall_ns": str(time.time_ns())}
        if scenario is not None:
            meta["scenario"] = msgspec.json.encode(without_recorders(scenario)).decode()
        self.sink.metadata(META_RUN, meta)

    @property
    def sim_span_s(self) -> float:
        """Simulated seconds between the first and the newest message."""
        return 0.0 if self.first_ns is None else (self.last_ns - self.first_ns) / 1e9

    def add(self, key: str, payload: bytes, received_ns: int) -> m.Msg | None:
        """Record one payload received on ``key`` at wall time ``received_ns``; returns
        it decoded (None if it does not decode)."""
        try:
            msg: m.Msg = codec.decode_any(payload)
        except codec.DecodeError as exc:
            self.rejects.reject(exc.kind, f"{key}: {exc.detail}")
            # still on the record, at the newest simulation time seen (it carries none we trust)
            self.sink.write(self.sink.raw_channel(key), payload, log_time_ns=self.last_ns,
                            publish_time_ns=received_ns)
            self.kinds["undecodable"] += 1
            return None
        if isinstance(msg, m.Tick):
            self._frames_promised.update((pair, msg.step) for pair in msg.cameras_rendered)
        elif isinstance(msg, m.CameraImage):
            self._frames_seen.add((f"{msg.robot_id}/{msg.camera}", msg.step))
            if not self.options.images:
                self.skipped_images += 1
                return msg
            if self.options.image_scale != 1.0:
                msg = scale_image(msg, self.options.image_scale)
                payload = codec.encode(msg)
        stamp = msg.stamp_ns
        self.first_ns = stamp if self.first_ns is None else min(self.first_ns, stamp)
        self.last_ns = max(self.last_ns, stamp)
        self.sink.write(self.sink.raw_channel(key), payload, log_time_ns=stamp, publish_time_ns=received_ns,
                        sequence=msg.seq)
        self.kinds[type(msg).__name__] += 1
        if self.views is not None:
            try:
                views = self.views.views(key, msg)
            except Exception as exc:  # a view is a convenience: never lose the recording over one
                self.rejects.reject("foxglove_view", f"{key}: {type(exc).__name__}: {exc}")
                return msg
            for topic, schema, data in views:
                self.sink.write(self.sink.foxglove_channel(topic, schema), data, log_time_ns=stamp,
                                publish_time_ns=received_ns)
        return msg

    def stats(self) -> dict[str, int]:
        """Counters: messages per type, rejects per kind, skipped images, totals."""
        out = {f"messages_{k}": v for k, v in sorted(self.kinds.items())}
        out.update(self.rejects.as_counters())
        out.update(skipped_images=self.skipped_images, mcap_messages=self.sink.messages,
                   mcap_payload_bytes=self.sink.bytes, images_missing=len(self._frames_promised - self._frames_seen))
        return out

    def close(self, extra: dict[str, int] | None = None) -> dict[str, int]:
        """Write the stats metadata and the summary; returns the stats."""
        stats = self.stats() | (extra or {})
        try:
            self.sink.metadata(META_STATS, {k: str(v) for k, v in stats.items()})
        finally:
            self.sink.close()
        return stats
