"""The JSON Schema of the wire messages in their msgpack form (``docs/messages.schema.json``).

It describes what a msgpack decoder in any language sees, not msgspec's JSON form: every
message is a map with string keys, ``type`` holding the message's tag; fields that are
Python tuples are arrays; ``bytes`` fields are msgpack *bin* (raw bytes), which JSON
Schema has no type for: they are marked ``"format": "binary"`` (the OpenAPI idiom) with
``contentMediaType: application/octet-stream`` and no ``type``, so a validator checks
them through a format checker for ``binary`` (:func:`validator` registers one that
accepts ``bytes`` only, what msgpack-python decodes bin to).  The root is a ``oneOf``
over every message, so one schema validates any payload; each message's definition
names its Zenoh encoding in ``x-zenoh-encoding``.
"""

from __future__ import annotations

import json
from typing import Any, Final

import msgspec

from tagswarm.protocol import wire

BINARY: Final = {"format": "binary", "contentMediaType": "application/octet-stream",
                 "description": "msgpack bin: raw bytes (not a string, not base64)"}
_SCHEMA_ID: Final = "https://json-schema.org/draft/2020-12/schema"


def _to_msgpack_form(node: Any) -> Any:
    """msgspec's JSON schema with every base64-string ``bytes`` node replaced by :data:`BINARY`."""
    if isinstance(node, dict):
        if node.get("type") == "string" and node.get("contentEncoding") == "base64":
            return dict(BINARY)
        return {k: _to_msgpack_form(v) for k, v in node.items()}
    if isinstance(node, list):
        return [_to_msgpack_form(v) for v in node]
    return node


def schema_dict() -> dict[str, Any]:
    """The schema as a dict (see the module docstring)."""
    types = list(wire.MESSAGE_TYPES)
    _, components = msgspec.json.schema_components(types, ref_template="#/$defs/{name}")
    defs = _to_msgpack_form(components)
    for cls in types:
        defs[cls.__name__]["x-zenoh-encoding"] = wire.encoding_of(cls)
    return {
        "$schema": _SCHEMA_ID,
        "title": "tagswarm wire messages (msgpack form)",
        "description": "One msgpack map per Zenoh sample; validate the decoded map against this schema. "
                       "Fields marked format 'binary' are msgpack bin (raw bytes). "
                       "See docs/protocol.md for keys, units and frames.",
        "oneOf": [{"$ref": f"#/$defs/{cls.__name__}"} for cls in types],
        "$defs": defs,
    }


def schema_text() -> str:
    """The schema file's text (stable: sorted keys, two-space indent)."""
    return json.dumps(schema_dict(), indent=2, sort_keys=True) + "\n"


def validator(schema: dict[str, Any] | None = None) -> Any:
    """A ``jsonschema`` validator of the msgpack form whose ``binary`` format accepts only
    ``bytes``.  jsonschema is a development dependency: imported here, not at module load."""
    import jsonschema

    checker = jsonschema.FormatChecker()
    checker.checks("binary")(lambda value: isinstance(value, bytes))
    return jsonschema.Draft202012Validator(schema or schema_dict(), format_checker=checker)
