"""JSON control messages: round trips, validation naming the field, garbage rejected cleanly."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.protocol.errors import MessageError, ProtocolError
from facecast.protocol.messages import (
    ErrorMessage,
    FapMessage,
    ProducerHello,
    Ready,
    SessionCreate,
    Stats,
    Status,
    ViewerHello,
    dump_message,
    parse_message,
)

EXAMPLES = [
    ProducerHello(input="audio", rate=16000, sample_format="i16"),
    ProducerHello(
        input="markers",
        markers=["LBRO", "RBRO", "HEAD1"],
        units="mm",
        layout={
            "markers": {"LBRO": {"fp": "4.1"}, "RBRO": {"vertex": 12}, "HEAD1": {}},
            "stable": ["HEAD1"],
        },
    ),
    ProducerHello(),
    Ready(session="ab", input="fap", fps=60.0, max_fps=250.0, vertex_count=2000),
    ViewerHello(
        session="ab",
        face="default:2k",
        topology_url="/v1/faces/default%3A2k/topology",
        vertex_count=2000,
        encoding="i16",
        fps=60.0,
        input="fap",
        producer_connected=True,
    ),
    ErrorMessage(code=4400, message="bad", where="hello.rate", fatal=True, seq=3),
    FapMessage(
        seq=4,
        t=0.04,
        wall=1.7e9,
        faps={3: 120.0, 19: -50.5},
        viseme=(1, 2, 30),
        expression=(1, 63, 0, 0),
    ),
    Stats(frames_in=3, viewers=2, deform_ms_mean=1.5, producer_connected=True),
    Status(producer_connected=False, viewers=1, last_seq=41),
]


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: f"{m.type}-{getattr(m, 'role', '')}")
def test_round_trip(msg):
    text = dump_message(msg)
    assert json.loads(text)["type"] == msg.type
    assert parse_message(text) == msg
    assert parse_message(text.encode()) == msg


def test_hello_is_told_apart_by_role():
    assert isinstance(parse_message('{"type": "hello", "role": "producer"}'), ProducerHello)
    with pytest.raises(MessageError, match="role"):
        parse_message('{"type": "hello"}')


@pytest.mark.parametrize(
    ("text", "where", "match"),
    [
        ('{"type": "fap", "t": 0, "faps": {"2": 1}}', "fap.faps", "low-level FAP"),
        ('{"type": "fap", "t": 0, "faps": {"70": 1}}', "fap.faps", "low-level FAP"),
        ('{"type": "fap", "t": 0, "viseme": [15, 0, 0]}', "fap.viseme", "viseme"),
        ('{"type": "fap", "t": 0, "expression": [1, 64, 0, 0]}', "fap.expression", "expression"),
        ('{"type": "fap"}', "fap.t", "required"),
        ('{"type": "fap", "t": 0, "extra": 1}', "fap.extra", "not permitted"),
        ('{"type": "hello", "role": "producer", "rate": -1}', "hello:producer.rate", "greater"),
        (
            '{"type": "hello", "role": "producer", "input": "video"}',
            "hello:producer.input",
            "'fap', 'audio' or 'markers'",
        ),
        ('{"type": "nope"}', "type", "unknown message type"),
        ("[]", "", "JSON object"),
        ("{", "", "not JSON"),
    ],
)
def test_invalid_messages_name_the_field(text, where, match):
    with pytest.raises(MessageError, match=match) as e:
        parse_message(text)
    assert e.value.where == where
    assert isinstance(e.value, ProtocolError) and e.value.close_code == 4400


def test_nan_and_oversize_are_refused():
    with pytest.raises(MessageError):
        parse_message('{"type": "fap", "t": NaN}')
    with pytest.raises(MessageError, match="limit"):
        parse_message('{"type": "stats", "x": "' + "a" * 300_000 + '"}')


def test_session_create_defaults_and_limits():
    assert SessionCreate().input == "fap" and SessionCreate().fps == 60.0
    with pytest.raises(ValueError):
        SessionCreate(fps=0)
    with pytest.raises(ValueError):
        SessionCreate(input="video")


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=4),
    max_leaves=12,
)


@settings(max_examples=300)
@given(
    st.one_of(
        st.text(max_size=200),
        st.binary(max_size=200),
        st.dictionaries(
            st.sampled_from(["type", "role", "t", "faps", "seq", "code", "message", "rate"]),
            json_values,
            max_size=5,
        ).map(json.dumps),
        st.fixed_dictionaries(
            {"type": st.sampled_from(["hello", "fap", "error", "stats", "status", "ready"])},
            optional={
                "role": st.sampled_from(["producer", "viewer", 3]),
                "t": json_values,
                "faps": json_values,
            },
        ).map(json.dumps),
    )
)
def test_any_input_parses_or_raises_message_error(text):
    try:
        parse_message(text)
    except MessageError:
        pass
