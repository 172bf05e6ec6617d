"""pybullet, imported without its build-time banner on stderr (it would turn
every one-line error message of ours into two lines)."""

from __future__ import annotations

import os
import sys
from types import ModuleType


def _quiet_import() -> ModuleType:
    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        import pybullet
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)
    return pybullet


pb = _quiet_import()
