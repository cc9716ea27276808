"""The layers of a live session over REST, and scoped producer tokens.

- ``POST /v1/sessions/{id}/tokens`` (admin key or the session's producer token): a producer token
  that may drive only the roles listed (``protocol.layers.TokenCreate``).
- ``GET /v1/sessions/{id}/layers``: the session's layers (set here, and connected producers').
- ``PUT /v1/sessions/{id}/layers/{name}``: set a layer (idle, expression, gaze, head:
  ``protocol.layers.LayerSpec``); ``PATCH`` changes some of its fields; ``GET`` reads it;
  ``DELETE`` removes it (``DELETE .../layers`` removes them all).

Authorised by the admin key or a producer token of the session (``Authorization: Bearer``, or
``?token=`` as the demo routes take it); a scoped token reaches only the layers of its roles.
Bodies are parsed here, so that a malformed one is a 400 naming the field (``protocol.layers``).
"""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter, Request, Response, status

from ...protocol.errors import Forbidden, MessageError, PayloadTooLarge
from ...protocol.layers import (
    LAYER_NAME_PATTERN,
    LayerInfo,
    LayerList,
    TokenCreate,
    TokenCreated,
    parse_layer,
    patch_layer,
)
from ...protocol.rest import ErrorBody
from ..errors import Unauthorized
from ..live.mixing import Spec
from ..live.roles import ALL_ROLES
from ..live.session import LiveSession
from .routes_sessions import registry
from .security import bearer, same

router = APIRouter(
    prefix="/v1/sessions/{session_id}",
    tags=["sessions"],
    responses={
        400: {"model": ErrorBody},
        401: {"model": ErrorBody},
        403: {"model": ErrorBody},
        404: {"model": ErrorBody},
    },
)

#: Largest layer or token request body, bytes.
MAX_BODY = 64 * 1024


class _Unauthorised(Unauthorized):
    status = 401

    def __init__(self) -> None:
        super().__init__(
            "send the admin key or a producer token of this session ('Authorization: Bearer "
            "<token>' or ?token=...)",
            where="token",
        )


class _NotYours(Forbidden):
    status = 403


class _TooLarge(PayloadTooLarge):
    status = 413


def _roles(request: Request, session: LiveSession, token: str | None) -> frozenset[str]:
    """The roles the caller may act for: all with the admin key, else its producer token's."""
    sent = bearer(request) or token
    if same(sent, request.app.state.admin_key):
        return ALL_ROLES
    roles = session.grants.roles_of(sent)
    if roles is None:
        raise _Unauthorised
    return roles


def _may(roles: frozenset[str], kind: str, name: str) -> None:
    if kind not in roles:
        raise _NotYours(
            f"this token may drive the role(s) {', '.join(sorted(roles))}; layer {name!r} is a "
            f"'{kind}' layer",
            where="token",
        )


def _name(name: str) -> str:
    import re

    if not re.fullmatch(LAYER_NAME_PATTERN, name):
        raise MessageError(
            "a layer name is 1-32 letters, digits, '_' or '-' (e.g. 'smile', 'idle')",
            where="name",
        )
    return name


async def _json(request: Request) -> Any:
    """The request's JSON body (at most ``MAX_BODY`` bytes); ``MessageError`` if it is not JSON."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > MAX_BODY:
        raise _TooLarge(f"a layer body is at most {MAX_BODY} bytes", where="body")
    raw = bytearray()
    async for chunk in request.stream():
        raw += chunk
        if len(raw) > MAX_BODY:
            raise _TooLarge(f"a layer body is at most {MAX_BODY} bytes", where="body")
    try:
        return json.loads(raw)
    except (ValueError, UnicodeDecodeError) as e:
        raise MessageError(f"the body is not JSON: {e}", where="body") from None
    except RecursionError:
        raise MessageError("the body nests too deeply to be a layer", where="body") from None


def _reach(
    request: Request, session_id: str, name: str, token: str | None
) -> tuple[LiveSession, Spec | None]:
    """The session and the spec of its REST layer ``name`` (None: no such layer), once the
    caller is known (401) and may reach that layer's kind (403)."""
    session = registry(request.app).get(session_id)
    roles = _roles(request, session, token)
    old = session.mix.spec(_name(name))
    if old is not None:
        _may(roles, old.kind, name)
    return session, old


@router.post("/tokens", status_code=status.HTTP_201_CREATED, response_model=TokenCreated)
async def create_token(session_id: str, request: Request, token: str | None = None) -> TokenCreated:
    """A producer token for some roles only (the admin key or the full producer token mints)."""
    session = registry(request.app).get(session_id)
    if _roles(request, session, token) != ALL_ROLES:
        raise _NotYours(
            "a scoped token cannot mint tokens; use the admin key or the session's producer token",
            where="token",
        )
    try:
        body = TokenCreate.model_validate(await _json(request))
    except ValueError as e:  # pydantic's ValidationError is a ValueError
        raise MessageError(_first_error(e), where="roles") from None
    return TokenCreated(
        session=session_id, token=session.grants.mint(body.roles), roles=list(body.roles)
    )


def _first_error(e: ValueError) -> str:
    errors = getattr(e, "errors", None)
    if callable(errors):
        first = errors()[0]
        return f"{first['msg']} ({'.'.join(str(x) for x in first['loc'])})"
    return str(e)


@router.get("/layers", response_model=LayerList)
async def list_layers(session_id: str, request: Request, token: str | None = None) -> LayerList:
    session = registry(request.app).get(session_id)
    _roles(request, session, token)
    return LayerList(session=session_id, layers=session.mix.infos())


@router.delete("/layers", status_code=status.HTTP_204_NO_CONTENT)
async def clear_layers(session_id: str, request: Request, token: str | None = None) -> Response:
    """Remove every REST layer the caller may reach."""
    session = registry(request.app).get(session_id)
    session.mix.clear(_roles(request, session, token))
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/layers/{name}", response_model=LayerInfo)
async def get_layer(
    session_id: str, name: str, request: Request, token: str | None = None
) -> LayerInfo:
    session = registry(request.app).get(session_id)
    _roles(request, session, token)
    return session.mix.info(_name(name))


@router.put("/layers/{name}", response_model=LayerInfo)
async def put_layer(
    session_id: str, name: str, request: Request, token: str | None = None
) -> LayerInfo:
    """Set (or replace) the layer ``name``: its body is a layer (``kind``: idle, expression, gaze,
    head, with its fields); it takes effect from the next frame."""
    session = registry(request.app).get(session_id)
    roles = _roles(request, session, token)
    spec = parse_layer(await _json(request))
    _may(roles, spec.kind, _name(name))
    old = session.mix.spec(name)
    if old is not None:
        _may(roles, old.kind, name)
    return session.mix.set(name, spec)


@router.patch("/layers/{name}", response_model=LayerInfo)
async def patch_layer_route(
    session_id: str, name: str, request: Request, token: str | None = None
) -> LayerInfo:
    """Change some fields of the layer ``name`` (its timing restarts from now)."""
    session, old = _reach(request, session_id, name, token)
    if old is None:
        raise session.mix.missing(name)
    return session.mix.set(name, patch_layer(old, await _json(request)))


@router.delete("/layers/{name}", status_code=status.HTTP_204_NO_CONTENT)
async def delete_layer(
    session_id: str, name: str, request: Request, token: str | None = None
) -> Response:
    session, _ = _reach(request, session_id, name, token)
    session.mix.remove(name)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
