"""Which key expression ``tagswarm spy KEYEXPR`` subscribes to (no network)."""

from __future__ import annotations

import pytest

from tagswarm.protocol.keys import Keys
from tagswarm.spy.spy import absolute_keyexpr


@pytest.mark.parametrize(("given", "subscribed"), [
    ("robot/1/odometry", "tagswarm/lab/robot/1/odometry"),
    ("/robot/*/status", "tagswarm/lab/robot/*/status"),
    ("tagswarm/other/**", "tagswarm/other/**"),
    ("**", "**"),
    ("*/lab/world/tick", "*/lab/world/tick"),
])
def test_a_key_expression_is_relative_to_the_run_unless_it_is_absolute(given: str, subscribed: str) -> None:
    assert absolute_keyexpr(given, Keys("lab")) == subscribed
