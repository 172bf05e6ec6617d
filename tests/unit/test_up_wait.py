"""``tagswarm up`` starts its clients only once the world's router accepts connections
(:func:`tagswarm.up.wait_listening`); probed here on Unix sockets (no network)."""

from __future__ import annotations

import socket
import time
from pathlib import Path

from tagswarm.up import wait_listening


def test_a_listening_unix_socket_is_found_at_once(tmp_path: Path) -> None:
    path = tmp_path / "router.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as srv:
        srv.bind(str(path))
        srv.listen()
        t0 = time.monotonic()
        assert wait_listening(f"unixsock-stream/{path}", lambda: True, 5.0)
        assert time.monotonic() - t0 < 1.0


def test_nobody_listening_gives_up_at_the_deadline(tmp_path: Path) -> None:
    t0 = time.monotonic()
    assert not wait_listening(f"unixsock-stream/{tmp_path / 'absent.sock'}", lambda: True, 0.3)
    assert 0.3 <= time.monotonic() - t0 < 2.0


def test_a_dead_world_stops_the_wait_at_once(tmp_path: Path) -> None:
    t0 = time.monotonic()
    assert not wait_listening(f"unixsock-stream/{tmp_path / 'absent.sock'}", lambda: False, 30.0)
    assert time.monotonic() - t0 < 1.0


def test_protocols_it_cannot_probe_are_left_to_zenoh() -> None:
    assert wait_listening("udp/127.0.0.1:7447", lambda: True, 0.1)
