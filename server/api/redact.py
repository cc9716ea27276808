"""Secrets out of log lines: ``token=`` (and ``key=``) values in URLs become ``***``; server paths
out of error messages (``path_scrubber``).

uvicorn's access log and its WebSocket ``[accepted]`` lines print each request's path with its
query string, where old clients still put session tokens (``?token=``). ``install()`` adds a
filter to the uvicorn loggers, which masks them before any handler sees them (filters on a logger
survive uvicorn's ``dictConfig`` of its handlers), and to the root logger's handlers, which
print every other record that propagates (facecast's own).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterable

_SECRET = re.compile(r"(?i)\b((?:producer_|viewer_|admin_)?(?:token|key))=[^&#\s\"']+")

#: Loggers whose own records are masked.
LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access")


def mask(text: str) -> str:
    """``text`` with every ``token=VALUE`` / ``key=VALUE`` query value replaced by ``***``."""
    return _SECRET.sub(r"\1=***", text)


def path_scrubber(roots: Iterable[str]) -> Callable[[str], str]:
    """A function that cuts every path under one of ``roots`` (folders a client must never see) in a
    text to its last part: ``/srv/data/jobs/x/input.fap`` -> ``input.fap``. One regular expression,
    compiled here once (the longest root wins); roots of one character (``/``) are ignored."""
    kept = sorted({r for r in roots if len(r) > 1}, key=len, reverse=True)
    if not kept:
        return lambda text: text
    pattern = re.compile("(?:" + "|".join(map(re.escape, kept)) + r")[^\s'\",:;)]*")

    def scrub(text: str) -> str:
        return pattern.sub(_last_part, text) if text else text

    return scrub


def _last_part(match: re.Match[str]) -> str:
    return match.group(0).rsplit("/", 1)[-1]


def _masked(value: object) -> object:
    return mask(value) if isinstance(value, str) else value


class SecretFilter(logging.Filter):
    """Masks token values in a record's message and its string arguments (never drops a record)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = mask(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(_masked(a) for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {k: _masked(v) for k, v in record.args.items()}
        return True


def install(names: tuple[str, ...] = LOGGERS) -> None:
    """Add one ``SecretFilter`` to each logger in ``names`` and to each handler of the root logger
    (idempotent)."""
    targets = [logging.getLogger(name) for name in names] + list(logging.getLogger().handlers)
    for target in targets:
        if not any(isinstance(f, SecretFilter) for f in target.filters):
            target.addFilter(SecretFilter())
