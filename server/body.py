"""Request bodies: their content types, JSON parsing, and the row limit (reading them: `admission`)."""

from __future__ import annotations

import json

from fastapi import Request

from neumip.core import contract as C

from neumip.server.errors import ApiError

MSGPACK_TYPES = ("application/msgpack", "application/x-msgpack", "application/vnd.msgpack")
"""Content types taken as msgpack (the first is `wire.MSGPACK_MEDIA_TYPE`)."""
JSON_TYPE = "application/json"


def media_type(request: Request) -> str | None:
    """The request's Content-Type without parameters, lower case; None if absent."""
    value = request.headers.get("content-type")
    if value is None:
        return None
    return value.split(";", 1)[0].strip().lower() or None


def header_int(value: str, name: str) -> int:
    """A header's non-negative decimal integer; 400 for anything else. ASCII digits only: ``str.isdigit``
    also takes superscripts such as "²", which ``int`` refuses; at most 18 of them (``int`` refuses
    strings of more than 4300 digits, and no length here comes near 10^18)."""
    text = value.strip()
    if not (0 < len(text) <= 18 and text.isascii() and text.isdigit()):
        raise ApiError(400, f"{name} must be a non-negative integer, got {value[:40]!r}")
    return int(text)


def parse_json(raw: bytes | memoryview, what: str = "body") -> object:
    """JSON text -> Python value; 400 saying where the JSON is broken (or that it nests too deep)."""
    try:
        return json.loads(bytes(raw))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ApiError(400, f"{what} is not valid JSON: {exc}") from None
    except RecursionError:
        raise ApiError(400, f"{what} nests too deep to be a query request") from None


def check_rows(shape: tuple[int, int], limit: int) -> int:
    """The answers (N K) a request of queries or query groups of `shape` (N, 5 + 2 K) asks for; 413 over the
    limit (N = 0 is valid: it answers nothing)."""
    answers = shape[0] * C.group_lights(shape[1])
    if answers > limit:
        raise ApiError(413, f"{answers} queries (a group of K lights counts K) is more than the limit of "
                            f"{limit} per request")
    return answers
