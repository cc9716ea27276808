"""The names of the vertex encodings and PCM sample formats, defined once.

Frames (``frames.py``, ``compact.py``), hello messages (``messages.py``), the REST/WebSocket
``?encoding=`` parameter and the CLI's ``--encoding`` choices all use these; a name is checked by
``parse_vertex_encoding``. The web client keeps its own copy of the names (``client/web/js``).
"""

from __future__ import annotations

from typing import Literal, get_args

from .errors import MessageError, show_token

__all__ = [
    "SAMPLE_FORMATS",
    "VERTEX_ENCODINGS",
    "SampleFormat",
    "VertexEncoding",
    "parse_vertex_encoding",
]

#: Vertex frames a viewer can ask for: ``f32`` (``VERTICES_F32``, 12 bytes a vertex), ``i16``
#: (``VERTICES_I16``, 6 bytes a vertex, per-frame offset and scale) or ``compact``
#: (``VERTICES_COMPACT``, error-bounded deltas against key frames).
VertexEncoding = Literal["f32", "i16", "compact"]
VERTEX_ENCODINGS: tuple[VertexEncoding, ...] = get_args(VertexEncoding)

#: PCM chunks a producer can send: ``i16`` (``PCM_I16``) or ``f32`` (``PCM_F32``).
SampleFormat = Literal["i16", "f32"]
SAMPLE_FORMATS: tuple[SampleFormat, ...] = get_args(SampleFormat)


def parse_vertex_encoding(text: str) -> VertexEncoding:
    """``text`` as a ``VertexEncoding``.

    Raises:
        MessageError: not one of ``VERTEX_ENCODINGS`` (``where="encoding"``).
    """
    for name in VERTEX_ENCODINGS:
        if text == name:
            return name
    raise MessageError(
        f"unknown encoding {show_token(text)}; use {', '.join(VERTEX_ENCODINGS[:-1])} or "
        f"{VERTEX_ENCODINGS[-1]}",
        where="encoding",
    )
