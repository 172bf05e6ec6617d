"""The base every scenario section builds on: :class:`Spec` and the ranges :data:`Pos`
and :data:`NonNeg`.

A module of its own so that :mod:`tagswarm.protocol.scenario_schema` and the section
modules it imports (:mod:`tagswarm.protocol.scenario_camera`) share one base without an
import cycle; :mod:`tagswarm.protocol.scenario_schema` re-exports these names.
"""

from __future__ import annotations

from typing import Annotated

import msgspec

Pos = Annotated[float, msgspec.Meta(gt=0)]
NonNeg = Annotated[float, msgspec.Meta(ge=0)]


class Spec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Base of scenario sections: frozen, keyword-only, typos are errors."""
