"""Small helpers of a test swarm: a free loopback endpoint, a unique run id, the run folder."""

from __future__ import annotations

import json
import os
import socket
import uuid
from pathlib import Path
from typing import Any

from tagswarm.recording.runrecorder import RunRecorder


def free_endpoint() -> str:
    """A loopback TCP endpoint on a port that is free right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def new_run_id(prefix: str = "t") -> str:
    """A run id no other swarm on this machine uses (pid + random: parallel pytest workers differ)."""
    return f"{prefix}{os.getpid()}-{uuid.uuid4().hex[:10]}"


def write_run(recorder: RunRecorder, run_dir: Path, info: dict[str, Any], *, plots: bool = False) -> dict[str, Any]:
    """The run folder as ``tagswarm up`` writes it: the recorder's files, then ``metrics.json``
    (and the report's plots with ``plots``).  Returns the metrics."""
    recorder.write(run_dir, info)
    if plots:
        from tagswarm.evaluation.report import write_report

        return write_report(run_dir)
    from tagswarm.evaluation.metrics import evaluate, load_run

    metrics = evaluate(load_run(run_dir)).metrics
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    return metrics
