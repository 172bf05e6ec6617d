"""Generated protocol docs are current and the schema describes real payloads."""

from __future__ import annotations

import json

from tagswarm import docs
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m


def test_generated_docs_are_up_to_date() -> None:
    assert docs.main(["--check"]) == 0, "run: python -m tagswarm.docs"


def test_schema_lists_every_message_and_its_fields() -> None:
    schema = json.loads(docs.schema())
    for cls in codec.MAX_BYTES:
        d = schema["$defs"][cls.__name__]
        assert set(cls.__struct_fields__) <= set(d["properties"]) and "type" in d["properties"]
    assert "robot/<id>/camera/<name>" in docs.markdown()
    assert schema["$defs"]["EncoderTicks"]["properties"]["left_ticks"]["type"] == "integer"
    assert m.Tick.__struct_config__.tag == "tick"
