"""The web viewer: ``/`` serves client/web/index.html, ``/static/...`` its scripts and styles."""
from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse

router = APIRouter(include_in_schema=False)

WEB_ROOT = Path(str(files("facecast.client"))) / "web"
MEDIA_TYPES = {".js": "text/javascript", ".css": "text/css", ".html": "text/html", ".svg": "image/svg+xml"}


@router.get("/")
def index() -> FileResponse:
    return FileResponse(WEB_ROOT / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"})


@router.get("/static/{path:path}")
def static(path: str) -> FileResponse:
    target = (WEB_ROOT / path).resolve()
    if not target.is_relative_to(WEB_ROOT.resolve()) or not target.is_file():
        raise HTTPException(404, detail=f"no such file in the web viewer: {path}")
    return FileResponse(target, media_type=MEDIA_TYPES.get(target.suffix), headers={"Cache-Control": "no-cache"})
