"""A BML uploaded with its recordings (REST jobs and live play): which uploaded file each speech means.

The client sends the BML as the ``file`` part and each recording as an ``audio`` part whose file
name is the name the BML's speech gives (its last path component: ``audio="voice/hi.wav"`` is
matched by an upload named ``hi.wav``). The server never opens a path a client names: the names
only select among the uploaded files, and every one must be used.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

from ...protocol.bml import BmlBlock, BmlError, Speech
from ..errors import InputError
from ..jobs.upload import safe_display_name
from .driver import read_block

__all__ = ["AUDIO_PART", "match_media"]

#: The form part of a BML's recordings.
AUDIO_PART = "audio"


def _last(name: str) -> str:
    return re.split(r"[\\/]", name)[-1]


def match_media(
    bml: Path,
    attachments: Sequence[tuple[str | None, Path, int]],
    *,
    display: str = "",
    into: Path | None = None,
) -> tuple[BmlBlock, dict[str, Path]]:
    """Parse the uploaded BML at ``bml`` and match its speeches' recordings to ``attachments``
    (``UploadParser.attachments``: client name, server path, bytes).

    Args:
        display: the client's name of the BML, for messages (instead of the server's path).
        into: move each recording to ``into / <the BML's name for it>`` (a job's folder, where the
            worker's driver finds it next to the BML); None: leave them in their folder (with
            the suffix of their name added).
    Returns:
        the block and ``{name as the BML writes it: server path}``.
    Raises:
        BmlError / InputError: malformed BML, a recording not uploaded, an upload not used or two
        uploads of one name.
    """
    try:
        block = read_block(bml)
    except BmlError as e:
        raise BmlError(e.reason, line=e.line, element=e.element, where=display) from None
    uploads: dict[str, Path] = {}
    for client_name, path, _ in attachments:
        key = safe_display_name(client_name, "")
        if not key:
            raise InputError(
                "an 'audio' part needs a file name: the name the BML's speech gives it "
                "(curl -F audio=@hello.wav)",
                where=AUDIO_PART,
            )
        if key in uploads:
            raise InputError(f"two 'audio' files are named {key!r}", where=AUDIO_PART)
        uploads[key] = path
    media: dict[str, Path] = {}
    for b in block.behaviours:
        if not isinstance(b, Speech) or b.audio is None or b.audio in media:
            continue
        twin = next((n for n in media if _last(n) == _last(b.audio)), None)
        if twin is not None:
            raise BmlError(
                f"audio {b.audio!r} and {twin!r} end in the same file name; an upload is matched "
                "by its file name: give the recordings different names",
                line=b.line,
                element="speech",
                where=display,
            )
        found = uploads.get(_last(b.audio))
        if found is None:
            raise BmlError(
                f"audio {b.audio!r} was not uploaded: send it as an 'audio' part named "
                f"{_last(b.audio)!r} (uploaded: {', '.join(sorted(uploads)) or 'none'})",
                line=b.line,
                element="speech",
                where=display,
            )
        media[b.audio] = found
    unused = sorted(set(uploads) - {_last(n) for n in media})
    if unused:
        raise InputError(
            f"uploaded audio {', '.join(map(repr, unused))} is not named by any speech of the BML",
            where=AUDIO_PART,
        )
    for name, path in list(media.items()):
        # a job's: beside the BML under its name (relative, without '..': parse_bml); a play's:
        # where it is, with its suffix (the audio decoder reads the type from it)
        dest = into / name if into is not None else path.with_name(path.name + Path(name).suffix)
        try:
            dest.parent.mkdir(parents=True, exist_ok=True)
            if dest.exists():
                raise FileExistsError(dest)
            path.replace(dest)
        except OSError:  # 'input.bml/a.wav', 'a.wav' and 'a.wav/b.wav': a name that clashes
            raise InputError(
                f"audio {name!r} cannot be kept under that name beside the BML (it clashes with "
                "another file of the job); name the recordings plainly, e.g. 'hello.wav'",
                where=AUDIO_PART,
            ) from None
        media[name] = dest
    return block, media
