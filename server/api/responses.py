"""JSON responses that never fail to serialise, whatever a client sent.

Error bodies echo client input (validation problems, face names...). That input may hold values
strict JSON cannot carry: NaN and infinities, bytes, lone surrogates, integers too long to print.
``safe_json`` turns them into plain strings; ``SafeJSONResponse`` uses it only when the fast path
fails, so normal responses cost nothing extra.
"""

from __future__ import annotations

import json
import math
from typing import Any

from fastapi.responses import JSONResponse

#: Longest string kept in an echoed value (characters); longer ones are cut with a marker.
MAX_ECHO_CHARS = 200
#: Largest integer printed as a number (bits); a larger one becomes a short description.
MAX_INT_BITS = 1024
#: Deepest nesting kept; deeper values become a short description.
MAX_DEPTH = 32


def safe_text(s: str, limit: int | None = None) -> str:
    """``s`` as valid UTF-8 text (lone surrogates escaped as ``\\udcxx``), cut to ``limit`` characters."""
    try:
        s.encode("utf-8")
    except UnicodeEncodeError:
        s = s.encode("utf-8", "backslashreplace").decode("utf-8")
    if limit is not None and len(s) > limit:
        s = s[:limit] + f"...({len(s) - limit} more characters)"
    return s


def safe_json(obj: Any, limit: int | None = MAX_ECHO_CHARS, _depth: int = 0) -> Any:
    """A copy of ``obj`` that ``json.dumps(allow_nan=False)`` and UTF-8 encoding always accept."""
    if _depth > MAX_DEPTH:
        return "(nested too deeply)"
    if obj is None or isinstance(obj, bool):
        return obj
    if isinstance(obj, int):
        return (
            int(obj)
            if obj.bit_length() <= MAX_INT_BITS
            else f"(an integer of {obj.bit_length()} bits)"
        )
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else repr(obj)
    if isinstance(obj, str):
        return safe_text(obj, limit)
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return safe_text(bytes(obj).decode("utf-8", "backslashreplace"), limit)
    if isinstance(obj, dict):
        return {safe_text(str(k), limit): safe_json(v, limit, _depth + 1) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [safe_json(v, limit, _depth + 1) for v in obj]
    try:
        text = str(obj)
    except Exception:
        text = f"({type(obj).__name__})"
    return safe_text(text, limit)


class SafeJSONResponse(JSONResponse):
    """A ``JSONResponse`` that falls back to ``safe_json`` when the content is not strict JSON."""

    def render(self, content: Any) -> bytes:
        try:
            return super().render(content)
        except (ValueError, TypeError, UnicodeEncodeError, RecursionError):
            return json.dumps(
                safe_json(content, limit=None),
                ensure_ascii=False,
                allow_nan=False,
                separators=(",", ":"),
            ).encode("utf-8")
