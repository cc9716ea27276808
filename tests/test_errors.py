"""One error tree (issue 13): every exception class facecast defines derives from ``FacecastError``,
splits into ``RemoteError`` (the peer's fault: 4xx) and ``LocalError`` (this side's: 5xx), and maps
through one function to the same HTTP status, close code and message on REST and WebSocket."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from functools import cache
from http import HTTPStatus

import pytest
from fastapi import WebSocket
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from facecast.protocol.errors import (
    INTERNAL_MESSAGE,
    CloseCode,
    FacecastError,
    InputError,
    LocalError,
    ProtocolError,
    RemoteError,
    error_reply,
)
from facecast.server.api import redact
from facecast.server.api.app import create_app
from facecast.server.api.config import ServerConfig
from facecast.server.api.errors import error_text, reply

#: Exceptions that are control flow, never an error a user sees: a job worker's stop signal (a
#: ``BaseException``, like ``KeyboardInterrupt``) and a viewer's socket found closed mid-send.
SIGNALS = {"Stop", "ViewerGone"}


@cache
def project_exceptions() -> tuple[type[BaseException], ...]:
    """Every exception class defined in facecast.protocol, .server and .client (all modules imported)."""
    found: dict[str, type[BaseException]] = {}
    for name in ("facecast.protocol", "facecast.server", "facecast.client"):
        package = importlib.import_module(name)
        modules = [package] + [
            importlib.import_module(m.name)
            for m in pkgutil.walk_packages(package.__path__, name + ".")
        ]
        for module in modules:
            for obj in vars(module).values():
                if (
                    inspect.isclass(obj)
                    and issubclass(obj, BaseException)
                    and obj.__module__ == module.__name__
                ):
                    found[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return tuple(found[k] for k in sorted(found))


def errors() -> list[type[FacecastError]]:
    return [c for c in project_exceptions() if issubclass(c, FacecastError)]


def instance(cls: type[FacecastError]) -> FacecastError:
    try:
        return cls("something was wrong", where="field")
    except TypeError:  # an error with a fixed message
        return cls()


def test_the_walk_finds_the_errors_of_every_layer():
    names = {c.__name__ for c in project_exceptions()}
    assert {
        "FapFormatError",
        "MarkerFileError",
        "TopologyError",
        "FrameError",
        "MessageError",
        "BadHello",
        "InputUnavailable",
        "MarkerFrameError",
        "OutputError",
        "PayloadTooLarge",
        "TooBusy",
        "LiveError",
        "RemoteJobError",
        "StreamError",
    } <= names


def test_every_exception_class_derives_from_the_one_root():
    outside = [
        f"{c.__module__}.{c.__qualname__}"
        for c in project_exceptions()
        if not issubclass(c, FacecastError) and c.__name__ not in SIGNALS
    ]
    assert outside == []


@pytest.mark.parametrize("cls", errors(), ids=lambda c: c.__qualname__)
def test_each_error_is_remote_4xx_or_local_5xx_with_a_defined_close_code(cls):
    assert HTTPStatus(cls.status) and CloseCode(cls.close_code)
    if cls is not FacecastError:
        assert issubclass(cls, RemoteError) != issubclass(cls, LocalError), "exactly one branch"
    if issubclass(cls, RemoteError):
        assert 400 <= cls.status < 500 and not 4500 <= cls.close_code < 4600
    else:
        assert 500 <= cls.status < 600 and 4500 <= cls.close_code < 4600
    r = error_reply(instance(cls))
    assert (r.status, r.close_code, r.remote, r.unexpected) == (
        cls.status,
        cls.close_code,
        issubclass(cls, RemoteError),
        False,
    )


def test_known_codes_of_today_are_kept():
    from facecast.protocol.fap_file import FapFormatError
    from facecast.server.api.routes_playback import Busy, TooBusy
    from facecast.server.errors import NotFound
    from facecast.server.live.inputs import BadHello, InputUnavailable
    from facecast.server.live.registry import TooMany, Unavailable
    from facecast.server.output.gltf import OutputError

    got = {
        c.__name__: (c.status, c.close_code)
        for c in (
            FapFormatError,
            BadHello,
            NotFound,
            Busy,
            TooMany,
            OutputError,
            InputUnavailable,
            Unavailable,
            TooBusy,
        )
    }
    assert got == {
        "FapFormatError": (400, 4400),
        "BadHello": (400, 4400),
        "NotFound": (404, 4404),
        "Busy": (409, 4409),
        "TooMany": (429, 4429),
        "OutputError": (422, 4422),
        "InputUnavailable": (503, 4503),
        "Unavailable": (503, 4503),
        "TooBusy": (503, 4503),
    }
    assert error_reply(TooBusy("all slots busy")).headers == {"Retry-After": "2"}


def test_parse_errors_stay_value_errors_but_the_branches_do_not():
    assert issubclass(ProtocolError, ValueError) and issubclass(ProtocolError, InputError)
    assert not issubclass(RemoteError, ValueError) and not issubclass(LocalError, ValueError)


def test_a_status_outside_its_branch_is_refused_when_the_class_is_defined():
    with pytest.raises(TypeError, match="4xx"):
        type("Wrong", (RemoteError,), {"status": 503})
    with pytest.raises(TypeError, match="5xx"):
        type("Wrong", (LocalError,), {"status": 404})
    gone = type("Gone", (RemoteError,), {"status": 410})
    assert gone.close_code == CloseCode.BAD_REQUEST  # an unlisted 4xx closes as a bad request


def test_anything_else_is_a_vague_server_fault():
    r = error_reply(RuntimeError("disk trouble at /srv/secret"))
    assert (r.status, r.close_code, r.message, r.unexpected) == (500, 4500, INTERNAL_MESSAGE, True)
    assert (
        error_reply(ValueError("bad")).status == 500
    )  # a bare ValueError is not the client's fault


# ------------------------------------------------------------------ the same on REST and WebSocket

KEY = "test-key"


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    app = create_app(
        ServerConfig(
            data_dir=tmp_path_factory.mktemp("errors"),
            admin_key=KEY,
            job_workers=0,
            face="default:2k",
            backend="numpy",
        )
    )
    by_name = {c.__qualname__ + "@" + c.__module__: c for c in errors()}
    secret = str(app.state.config.data_dir / "jobs" / "x" / "input.fap")

    def raise_it(name: str) -> None:
        if name == "boom":
            raise RuntimeError(f"disk trouble at {secret}")
        cls = by_name[name]
        try:
            raise cls(f"bad bytes in {secret}", where=secret)
        except TypeError:
            raise cls() from None

    @app.get("/_test/raise/{name}")
    async def rest(name: str) -> None:
        raise_it(name)

    @app.websocket("/_test/raise/{name}")
    async def ws(websocket: WebSocket, name: str) -> None:
        await websocket.accept()
        try:
            raise_it(name)
        except Exception as e:  # noqa: BLE001 - a shell answers every error
            r = reply(e, websocket.app)
            await websocket.send_text(error_text(r))
            await websocket.close(r.close_code)

    app.state.test_names = sorted(by_name) + ["boom"]
    return app


def test_rest_and_websocket_hear_the_same_status_code_and_message(app):
    client = TestClient(app, raise_server_exceptions=False)
    data_dir = str(app.state.config.data_dir)
    for name in app.state.test_names:
        resp = client.get(f"/_test/raise/{name}")
        body = resp.json()
        with client.websocket_connect(f"/_test/raise/{name}") as ws:
            message = ws.receive_json()
            with pytest.raises(WebSocketDisconnect) as closed:
                ws.receive_text()
        assert resp.status_code == body["status"], name
        assert closed.value.code == message["code"] and message["fatal"], name
        assert (message["message"], message["where"]) == (body["error"], body.get("where", "")), (
            name
        )
        assert data_dir not in resp.text and data_dir not in message["message"], name
        if name == "boom":
            assert (resp.status_code, message["code"], body["error"]) == (
                500,
                4500,
                INTERNAL_MESSAGE,
            )
        else:
            cls = next(c for c in errors() if f"{c.__qualname__}@{c.__module__}" == name)
            assert (resp.status_code, message["code"]) == (cls.status, cls.close_code), name
            if "bad bytes in" in body["error"]:  # not an error with a fixed message
                assert "bad bytes in input.fap" in body["error"], name  # the file's own name stays


# ------------------------------------------------------------------------------------ path scrubber


def test_the_path_scrubber_compiles_once_and_keeps_only_the_last_part(monkeypatch):
    scrub = redact.path_scrubber(["/srv/data", "/srv/data/jobs", "/", "/tmp"])
    monkeypatch.setattr(redact, "re", None)  # a call that compiled again would fail now
    text = "bad /srv/data/jobs/x/input.fap, see /tmp/facecast-1/upload and /srvx"
    assert scrub(text) == "bad input.fap, see upload and /srvx"
    assert scrub("") == "" and redact.path_scrubber(["/"])("/etc/passwd") == "/etc/passwd"
