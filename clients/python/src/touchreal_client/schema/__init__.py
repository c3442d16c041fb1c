"""The machine-readable contract of ``/v1/stream``: an AsyncAPI 3.0 document (``asyncapi.json`` here,
served by the service at ``GET /v1/asyncapi.json``) whose ``components.schemas`` are JSON Schemas
(draft-07, the dialect AsyncAPI schemas extend) of every JSON message: ``hello``, ``clock``,
``subscribed``, ``time`` (request and reply), ``error``, ``ended``, ``subscribe`` and the JSON
encoding of the spikes, channels and decoded frames. docs/stream-protocol.md is the prose.

>>> import jsonschema
>>> jsonschema.validate(msg, message_schema(server_message_schema(msg)))
"""

from __future__ import annotations

import copy
import json
from functools import lru_cache
from importlib.resources import files
from typing import Any

JSON_SCHEMA_DIALECT = "http://json-schema.org/draft-07/schema#"

#: ``type`` of a server -> client message -> its schema in ``components.schemas``.
SERVER_MESSAGES = {"hello": "hello", "clock": "clock", "subscribed": "subscribed", "time": "timeReply",
                   "error": "error", "ended": "ended", "spikes": "spikesFrame", "channels": "channelsFrame",
                   "decoded": "decodedFrame"}
#: ``type`` of a client -> server message -> its schema.
CLIENT_MESSAGES = {"subscribe": "subscribe", "time": "timeRequest"}


@lru_cache(maxsize=1)
def _document_text() -> str:
    return files(__package__).joinpath("asyncapi.json").read_text(encoding="utf-8")


def asyncapi(host: str | None = None) -> dict[str, Any]:
    """The AsyncAPI 3.0 document (a fresh copy); ``host`` (``HOST:PORT``) names the server that serves it."""
    doc = json.loads(_document_text())
    if host:
        doc["servers"]["service"]["host"] = host
    return doc


def message_schema(name: str) -> dict[str, Any]:
    """A standalone JSON Schema (draft-07) for the component schema ``name`` (e.g. ``"hello"``,
    ``"spikesFrame"``); KeyError for an unknown name."""
    schemas = json.loads(_document_text())["components"]["schemas"]
    if name not in schemas:
        raise KeyError(f"no schema {name!r}; known: {sorted(schemas)}")
    return {"$schema": JSON_SCHEMA_DIALECT, "$id": f"urn:touchreal:stream:v1:{name}",
            "allOf": [{"$ref": f"#/components/schemas/{name}"}], "components": {"schemas": copy.deepcopy(schemas)}}


def server_message_schema(msg: dict[str, Any]) -> str:
    """The schema name of a server -> client JSON message, by its ``type``; KeyError if unknown."""
    return SERVER_MESSAGES[msg["type"]]
