"""OpenAPI descriptions of the raw-body endpoints (their handlers read bytes, so FastAPI cannot infer them).

These schemas are documentation and the input of the schemathesis fuzz test; the handlers validate
every body themselves.
"""

from __future__ import annotations

from neumip.core import contract as C
from neumip.core import wire

ERROR_SCHEMA = {
    "type": "object",
    "required": ["error"],
    "properties": {"error": {"type": "string", "description": "What was wrong"}},
}
ERROR_RESPONSES = {
    status: {"description": text, "content": {"application/json": {"schema": ERROR_SCHEMA}}}
    for status, text in (
        (400, "Malformed request (bad body, shape, values, header or name)"),
        (404, "Unknown material or endpoint"),
        (408, "Body not complete within NEUMIP_BODY_TIMEOUT_S"),
        (413, "Body, JSON or row count over the limit"),
        (415, "Unsupported Content-Type or Content-Encoding"),
        (500, "The model failed or answered NaN/Inf (the message names the material)"),
        (503, "Queue or body budget full, or models still loading (see Retry-After); or the server stopping"),
    )
}

_ROW = {
    "type": "array",
    "items": {"type": "number"},
    "minItems": C.QUERY_DIM,
    "maxItems": C.group_width(C.MAX_LIGHTS),
    "description": f"{', '.join(C.QUERY_FIELDS)}; a query group of K lights adds wi_x, wi_y of each further "
    "light (5 + 2 K numbers, the same in every row)",
}
_BINARY = {"type": "string", "format": "binary"}

EVALUATE_BODY = {
    "required": True,
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "required": ["queries"],
                "properties": {"queries": {"type": "array", "items": _ROW}, "n": {"type": "integer"}},
            }
        },
        wire.MSGPACK_MEDIA_TYPE: {
            "schema": _BINARY,
            "description": 'msgpack map {"n": N, "lights": K, "queries": N*7 little-endian float32 bytes}, or '
            "N*(5 + 2 K) for query groups of K lights. \"lights\" is optional: with it the bytes must be exactly "
            "N rows of 5 + 2 K values (400 otherwise); without it the width is read from the byte count",
        },
    },
}
EVALUATE_RESPONSE = {
    "description": "RGB per query (3 K values a row for groups of K lights), in the request's format",
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "properties": {
                    "n": {"type": "integer"},
                    "rgb": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}},
                },
            }
        },
        wire.MSGPACK_MEDIA_TYPE: {"schema": _BINARY},
    },
}

_TENSOR = {
    "type": "object",
    "required": ["name", "shape", "datatype"],
    "properties": {
        "name": {"type": "string"},
        "shape": {"type": "array", "items": {"type": "integer"}},
        "datatype": {"type": "string"},
        "parameters": {"type": "object"},
        "data": {"type": "array"},
    },
}
INFER_BODY = {
    "required": True,
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "required": ["inputs"],
                "properties": {
                    "id": {"type": "string"},
                    "parameters": {"type": "object"},
                    "inputs": {"type": "array", "items": _TENSOR},
                    "outputs": {
                        "type": "array",
                        "items": {
                            "type": "object",
                            "required": ["name"],
                            "properties": {"name": {"type": "string"}, "parameters": {"type": "object"}},
                        },
                    },
                },
            }
        },
        "application/octet-stream": {
            "schema": _BINARY,
            "description": "JSON header (length in Inference-Header-Content-Length) then raw tensor bytes",
        },
    },
}
