"""The web viewer: ``/`` serves client/web/index.html, ``/static/...`` its scripts and styles.

``/docs`` (Swagger UI) and ``/redoc`` load their scripts from ``/docs-assets/...``, files shipped
by the ``fastapi-offline`` package: the API docs work on a machine without internet access.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from fastapi import APIRouter, HTTPException, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse

router = APIRouter(include_in_schema=False)

WEB_ROOT = Path(str(files("facecast.client"))) / "web"
MEDIA_TYPES = {
    ".js": "text/javascript",
    ".css": "text/css",
    ".html": "text/html",
    ".svg": "image/svg+xml",
    ".png": "image/png",
}
#: The docs assets served under ``/docs-assets/`` (the only files of the package that are).
DOCS_ASSETS = ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js", "favicon.png")


def docs_assets_root() -> Path:
    return Path(str(files("fastapi_offline"))) / "static"


@router.get("/")
def index() -> FileResponse:
    return FileResponse(
        WEB_ROOT / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"}
    )


@router.get("/static/{path:path}")
def static(path: str) -> FileResponse:
    try:
        target = (WEB_ROOT / path).resolve()
        found = target.is_relative_to(WEB_ROOT.resolve()) and target.is_file()
    except (ValueError, OSError):  # a NUL byte, a name too long for the file system
        found = False
    if not found:
        raise HTTPException(404, detail=f"no such file in the web viewer: {path}")
    return FileResponse(
        target, media_type=MEDIA_TYPES.get(target.suffix), headers={"Cache-Control": "no-cache"}
    )


@router.get("/docs")
def swagger_ui(request: Request) -> HTMLResponse:
    return get_swagger_ui_html(
        openapi_url=request.app.openapi_url,
        title=f"{request.app.title} API",
        swagger_js_url="/docs-assets/swagger-ui-bundle.js",
        swagger_css_url="/docs-assets/swagger-ui.css",
        swagger_favicon_url="/docs-assets/favicon.png",
        swagger_ui_parameters={"validatorUrl": None},
    )  # no call to an online validator


@router.get("/redoc")
def redoc(request: Request) -> HTMLResponse:
    return get_redoc_html(
        openapi_url=request.app.openapi_url,
        title=f"{request.app.title} API",
        redoc_js_url="/docs-assets/redoc.standalone.js",
        redoc_favicon_url="/docs-assets/favicon.png",
        with_google_fonts=False,
    )


@router.get("/docs-assets/{name}")
def docs_asset(name: str) -> FileResponse:
    if name not in DOCS_ASSETS:
        raise HTTPException(404, detail=f"no such docs asset: {name}")
    path = docs_assets_root() / name
    return FileResponse(
        path, media_type=MEDIA_TYPES.get(path.suffix), headers={"Cache-Control": "max-age=86400"}
    )
