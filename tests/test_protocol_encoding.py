"""The one encoding vocabulary: frames, hello messages, the ``?encoding=`` check and the CLI agree."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from facecast.protocol import frames as fr
from facecast.protocol.encoding import (
    SAMPLE_FORMATS,
    VERTEX_ENCODINGS,
    parse_vertex_encoding,
)
from facecast.protocol.errors import CloseCode, MessageError
from facecast.protocol.messages import ProducerHello, ViewerHello, parse_message


def test_the_names_are_the_wire_names():
    assert VERTEX_ENCODINGS == ("f32", "i16", "compact")
    assert set(SAMPLE_FORMATS) == {"i16", "f32"}


@pytest.mark.parametrize("name", VERTEX_ENCODINGS)
def test_every_name_parses_and_goes_into_a_viewer_hello(name):
    assert parse_vertex_encoding(name) == name
    hello = ViewerHello(
        session="s",
        face="f",
        topology_url="/t",
        vertex_count=3,
        encoding=name,
        fps=60.0,
        input="fap",
        producer_connected=False,
    )
    assert parse_message(hello.model_dump_json()) == hello


@pytest.mark.parametrize("text", ["", "F32", "int16", "f16", "compact ", "x" * 10_000])
def test_unknown_names_are_refused_with_the_names_to_use(text):
    with pytest.raises(MessageError) as e:
        parse_vertex_encoding(text)
    assert e.value.where == "encoding" and e.value.close_code == CloseCode.BAD_REQUEST
    assert "use f32, i16 or compact" in str(e.value) and len(str(e.value)) < 120


def test_the_single_frame_encoders_take_the_stateless_names():
    v = np.ones((4, 3), np.float32)
    for name in ("f32", "i16"):
        b = fr.encode_vertices(v, name, seq=0, t=0.0)
        assert len(b) == fr.vertex_frame_size(name, 4)
    with pytest.raises(ValueError):
        fr.encode_vertices(v, "compact", seq=0, t=0.0)  # stateful: compact.CompactEncoder


def test_a_producer_sample_format_is_a_pcm_format_not_a_vertex_encoding():
    for fmt in SAMPLE_FORMATS:
        assert ProducerHello(input="audio", rate=16000, sample_format=fmt).sample_format == fmt
    with pytest.raises(MessageError) as e:  # was accepted (and read as f32) before
        parse_message(
            json.dumps(
                {
                    "type": "hello",
                    "role": "producer",
                    "input": "audio",
                    "rate": 16000,
                    "sample_format": "compact",
                }
            )
        )
    assert e.value.where.endswith("sample_format")


def test_the_watch_command_offers_exactly_the_vocabulary():
    from facecast.client.commands import watch

    p = argparse.ArgumentParser()
    watch.add_arguments(p)
    (action,) = [a for a in p._actions if a.dest == "encoding"]
    assert tuple(action.choices) == VERTEX_ENCODINGS and action.default == "compact"
