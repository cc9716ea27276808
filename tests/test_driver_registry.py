"""The one driver registry: one name per input kind (``markers``), ``mocap`` accepted as its alias."""

from __future__ import annotations

import argparse
import importlib

import pytest

from facecast.protocol.messages import INPUT_KINDS, ProducerHello, SessionCreate, parse_message
from facecast.protocol.rest import JobOptions, JobStatus
from facecast.server.drivers import DRIVERS, SUFFIXES, input_kind
from facecast.server.errors import InputError
from facecast.server.live.inputs import load_driver_class


def test_the_registry_names_every_input_kind_once():
    assert tuple(DRIVERS) == (*INPUT_KINDS, "bml")
    assert INPUT_KINDS == ("fap", "audio", "markers")  # bml is a file kind, no session input
    assert dict(SUFFIXES.items()) == {
        ".fap": "fap",
        ".wav": "audio",
        ".flac": "audio",
        ".ogg": "audio",
        ".c3d": "markers",
        ".trc": "markers",
        ".csv": "markers",
        ".bml": "bml",
    }


@pytest.mark.parametrize("kind", INPUT_KINDS)
def test_every_driver_module_and_class_exists(kind):
    assert callable(importlib.import_module(DRIVERS[kind].batch).load)
    if DRIVERS[kind].live is not None:
        assert isinstance(load_driver_class(kind), type)


@pytest.mark.parametrize(
    ("name", "kind"),
    [
        ("a.FAP", "fap"),
        ("x/y.wav", "audio"),
        ("t.C3D", "markers"),
        ("t.trc", "markers"),
        ("t.csv", "markers"),
    ],
)
def test_input_kind_by_suffix(name, kind):
    assert input_kind(name) == kind


@pytest.mark.parametrize("name", ["a.mp4", "noext", "a.c3d.bak"])
def test_unknown_suffixes_are_refused(name):
    with pytest.raises(InputError, match="unsupported input type"):
        input_kind(name)


@pytest.mark.parametrize("sent", ["markers", "mocap"])
def test_a_client_may_send_either_name(sent):
    assert SessionCreate(input=sent).input == "markers"
    hello = parse_message(f'{{"type": "hello", "role": "producer", "input": "{sent}"}}')
    assert isinstance(hello, ProducerHello) and hello.input == "markers"


def test_other_names_are_still_refused():
    with pytest.raises(ValueError):
        SessionCreate(input="video")


def test_a_job_stored_under_the_old_name_shows_the_one_name():
    job = JobStatus(
        id="j",
        status="done",
        progress=1.0,
        input_name="t.c3d",
        input_kind="mocap",
        input_bytes=1,
        options=JobOptions(),
        attempts=1,
        created=0.0,
    )
    assert job.input_kind == "markers"


@pytest.mark.parametrize("sent", ["markers", "mocap"])
def test_the_session_command_takes_either_name(sent):
    from facecast.client.commands import session

    p = argparse.ArgumentParser()
    session.add_arguments(p)
    args = p.parse_args(["create", "--input", sent, "--url", "http://127.0.0.1:1"])
    assert args.input == sent  # sent as typed: the server reads the alias
