"""facecast.server: faces, drivers, deformation, sessions, jobs and the HTTP/WebSocket API."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("facecast")
except PackageNotFoundError:  # pragma: no cover - running from an uninstalled tree
    __version__ = "0.0.0"
