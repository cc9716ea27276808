"""Streaming ``multipart/form-data`` upload: the file part goes to disk as it arrives, with a limit.

Nothing is held in memory beyond one network chunk and small form fields. Client file names are
only used to guess the input type and for display; they never become paths.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from python_multipart import MultipartParser
from python_multipart.multipart import parse_options_header

from ..drivers import SUFFIXES
from ..errors import FacecastError, InputError, PayloadTooLarge, UnsupportedMedia

#: Form field values larger than this are refused (they are short options)...
MAX_FIELD_BYTES = 4096
#: ... except these, which carry content (a mocap marker layout is JSON of a few KiB).
FIELD_LIMITS = {"layout": 1024 * 1024, "text": 64 * 1024}
#: Form parts besides the file an upload may have.
MAX_FIELDS = 16
#: Files an upload may attach besides its input (a BML's recordings).
MAX_ATTACHMENTS = 8
#: Bytes of the file kept to recognise its type from content.
SNIFF_BYTES = 4096


def safe_display_name(name: str | None, default: str = "upload") -> str:
    """The last path component of a client file name, printable and at most 100 characters."""
    base = re.split(r"[\\/]", name or "")[-1]
    base = "".join(c for c in base if c.isprintable() and c not in '"<>|*?:').strip().lstrip(".")
    return base[:100] or default


class UploadParser:
    """Feeds request body chunks to python-multipart; writes the ``file_field`` part to ``dest``.

    After ``finish()``: ``fields`` (name -> str), ``filename`` (client's, unchecked text),
    ``size`` (bytes of the file), ``head`` (its first ``SNIFF_BYTES``).
    """

    #: Form fields that carry content, and their size limits (others: ``MAX_FIELD_BYTES``).
    field_limits: dict[str, int] = FIELD_LIMITS

    def __init__(
        self,
        boundary: bytes,
        dest: Path,
        limit: int,
        file_field: str = "file",
        kind_limit: Callable[[str], tuple[int, str]] | None = None,
        attachment_field: str | None = None,
    ):
        """``limit``: bytes of the file at most; ``kind_limit(kind) -> (bytes, variable)`` lowers it
        for the file's input kind (``fap`` | ``audio`` | ``markers``) once its first bytes are known.

        ``attachment_field``: parts of that name are more files (a BML's recordings: ``audio``), at
        most ``MAX_ATTACHMENTS``, each within the ``audio`` kind's limit and all together within
        ``limit``; written beside ``dest`` and listed in ``attachments`` as ``(client file name,
        path, bytes)``."""
        self.attachment_field = attachment_field
        self.attachments: list[tuple[str | None, Path, int]] = []
        self._attachment_limit = (
            min(limit, kind_limit("audio")[0]) if kind_limit is not None else limit
        )
        self._total_limit = limit
        self.dest = dest
        self.limit = limit
        self.limit_variable = "FACECAST_MAX_UPLOAD_BYTES"
        self.kind: str | None = None
        self._kind_limit = kind_limit
        self.file_field = file_field
        self.fields: dict[str, str] = {}
        self.filename: str | None = None
        self.size = 0
        self.head = b""
        self.got_file = False
        self._headers: dict[bytes, bytes] = {}
        self._hname = b""
        self._hvalue = b""
        self._name: str | None = None
        self._is_file = False
        self._value = bytearray()
        self._fh = None
        self._attaching = False
        self._parser = MultipartParser(
            boundary,
            {
                "on_part_begin": self._part_begin,
                "on_header_field": self._header_field,
                "on_header_value": self._header_value,
                "on_header_end": self._header_end,
                "on_headers_finished": self._headers_finished,
                "on_part_data": self._part_data,
                "on_part_end": self._part_end,
            },
        )

    # -- python-multipart callbacks --------------------------------------------------------------
    def _part_begin(self) -> None:
        self._headers = {}
        self._hname = self._hvalue = b""

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._hname += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self._hvalue += data[start:end]

    def _header_end(self) -> None:
        self._headers[self._hname.lower()] = self._hvalue
        self._hname = self._hvalue = b""

    def _headers_finished(self) -> None:
        _, opts = parse_options_header(self._headers.get(b"content-disposition", b""))
        self._name = opts.get(b"name", b"").decode("utf-8", "replace")
        self._value = bytearray()
        self._is_file = self._name == self.file_field
        if self.attachment_field is not None and self._name == self.attachment_field:
            self._begin_attachment(opts.get(b"filename"))
            return
        if not self._is_file and len(self.fields) >= MAX_FIELDS:
            raise InputError(f"more than {MAX_FIELDS} form fields", where="form")
        if self._is_file:
            if self.got_file:
                raise InputError("send exactly one 'file' part", where="file")
            self.got_file = True
            fn = opts.get(b"filename")
            self.filename = fn.decode("utf-8", "replace") if fn is not None else None
            # open across the parser's callbacks; _part_end, finish and abort close it
            self._fh = open(self.dest, "wb")  # noqa: SIM115

    def _begin_attachment(self, filename: bytes | None) -> None:
        if len(self.attachments) >= MAX_ATTACHMENTS:
            raise InputError(
                f"more than {MAX_ATTACHMENTS} '{self.attachment_field}' files", where="form"
            )
        path = self.dest.with_name(f"{self.dest.name}.attachment{len(self.attachments)}")
        name = filename.decode("utf-8", "replace") if filename is not None else None
        self.attachments.append((name, path, 0))
        self._is_file = False
        self._attaching = True
        self._fh = open(path, "wb")  # noqa: SIM115 - closed in _part_end, finish or abort

    def _attachment_data(self, chunk: bytes) -> None:
        name, path, size = self.attachments[-1]
        size += len(chunk)
        self.attachments[-1] = (name, path, size)
        total = self.size + sum(a[2] for a in self.attachments)
        if size > self._attachment_limit or total > self._total_limit:
            limit = min(self._attachment_limit, self._total_limit)
            raise PayloadTooLarge(
                f"the upload's files are larger than this server's limit ({limit} bytes for a "
                f"recording, {self._total_limit} in all); send shorter recordings",
                where=self.attachment_field or "file",
            )
        self._fh.write(chunk)

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        chunk = data[start:end]
        if self._attaching:
            self._attachment_data(chunk)
        elif self._is_file:
            self.size += len(chunk)
            if len(self.head) < SNIFF_BYTES:
                self.head += chunk[: SNIFF_BYTES - len(self.head)]
                if len(self.head) >= SNIFF_BYTES:
                    self._check_kind()
            self._check_size()
            self._fh.write(chunk)
        else:
            self._value += chunk
            limit = self.field_limits.get(self._name or "", MAX_FIELD_BYTES)
            if len(self._value) > limit:
                raise InputError(
                    f"form field is longer than {limit} bytes", where=self._name or "form"
                )

    def _check_kind(self) -> None:
        """Learn the file's input kind from its name and first bytes; apply that kind's limit."""
        if self.kind is not None:
            return
        from ..drivers import input_kind

        self.kind = input_kind("input" + input_suffix(self.filename, self.head))
        if self._kind_limit is not None:
            limit, variable = self._kind_limit(self.kind)
            if limit < self.limit:
                self.limit, self.limit_variable = limit, variable

    def _check_size(self) -> None:
        if self.size > self.limit:
            what = f"{self.kind} input" if self.kind else "a file"
            raise PayloadTooLarge(
                f"the uploaded file is larger than this server's limit of {self.limit} bytes for {what}; "
                f"send a smaller file (split long recordings) or raise {self.limit_variable} on the server",
                where="file",
            )

    def _part_end(self) -> None:
        if self._attaching:
            self._attaching = False
            self._fh.close()
            self._fh = None
        elif self._is_file:
            if self.size:
                self._check_kind()
                self._check_size()
            self._fh.close()
            self._fh = None
        elif self._name:
            self.fields[self._name] = self._value.decode("utf-8", "replace")

    # -- driving ---------------------------------------------------------------------------------
    def write(self, chunk: bytes) -> None:
        self._parser.write(chunk)

    def finish(self) -> None:
        self._parser.finalize()
        if not self.got_file:
            raise InputError(
                "no file in the upload; send the input as a multipart part named 'file'",
                where="file",
            )
        if self._fh is not None:
            raise InputError("the upload ended in the middle of the file part", where="file")

    def abort(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
        self.dest.unlink(missing_ok=True)
        for _, path, _ in self.attachments:
            path.unlink(missing_ok=True)


async def refuse_declared_oversize(request: Any, limit: int, overhead: int, advice: str) -> None:
    """Refuse, before reading it, a body whose declared ``Content-Length`` exceeds ``limit`` bytes of
    file plus ``overhead`` bytes of form (``PayloadTooLarge``, with ``advice`` on what to send)."""
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > limit + overhead:
        await drain(request, 0)
        raise PayloadTooLarge(
            f"the upload is {int(declared)} bytes, more than this server's limit of {limit} "
            f"bytes for {advice}",
            where="file",
        )


async def receive(request: Any, parser: UploadParser) -> None:
    """Stream ``request``'s body into ``parser`` and finish it (the one upload loop of the routes).

    A refusal on the way (too large, unknown type, bad framing: a ``FacecastError``) removes the
    partial file and reads the rest of the body, so that the still-sending client hears the answer;
    any other failure is malformed multipart framing, refused as an ``InputError`` naming the body.
    """
    received = 0
    try:
        async for chunk in request.stream():
            received += len(chunk)
            parser.write(chunk)
        parser.finish()
    except FacecastError:
        parser.abort()
        await drain(request, received)
        raise
    except Exception as e:  # noqa: BLE001 - the multipart parser's own errors: malformed framing
        parser.abort()
        raise InputError(
            f"could not read the multipart upload ({str(e)[:200]}); send a multipart/form-data "
            "body with a 'file' part",
            where="body",
        ) from None


#: Bytes of a refused request the server still reads (and discards) so the client sees the answer.
DRAIN_LIMIT = 64 * 1024 * 1024


async def drain(request, already: int = 0, limit: int = DRAIN_LIMIT) -> None:
    """Read and discard the rest of a refused request body (at most ``limit`` bytes in all), so the
    client, still sending, can read the error instead of a reset connection."""
    n = already
    try:
        async for chunk in request.stream():
            n += len(chunk)
            if n > limit:
                break
    except Exception:  # noqa: BLE001 - best effort: whatever ends the read ends the drain
        pass


def upload_dir(data_dir: Path) -> Path:
    """``<data_dir>/tmp``: where uploads wait while they are read (emptied at each server start)."""
    path = Path(data_dir) / "tmp"
    path.mkdir(parents=True, exist_ok=True)
    return path


def clear_upload_dir(data_dir: Path) -> int:
    """Delete what a previous server left in ``<data_dir>/tmp`` (uploads of a crash); the count."""
    import shutil

    root = upload_dir(data_dir)
    n = 0
    for p in root.iterdir():
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        n += 1
    return n


def parse_layout(text: str) -> dict:
    """A mocap marker layout sent as content (its JSON text), checked; InputError otherwise.

    Layouts travel as content, never as names of server files: a JSON string (a path) is refused.
    """
    try:
        data = json.loads(text)
    except (
        ValueError,
        RecursionError,
    ) as e:  # JSONDecodeError, integers over 4300 digits, deep nesting
        raise InputError(
            f"the layout is not JSON ({str(e)[:200]}); send the layout file's content "
            "(curl -F layout=@take.layout.json)",
            where="layout",
        ) from None
    if not isinstance(data, dict):
        raise InputError(
            "the layout must be the layout's JSON content, an object with 'markers' and "
            "'stable' (curl -F layout=@take.layout.json); the server never opens files "
            "named by a client",
            where="layout",
        )
    from ..mocap.layout import load_layout

    try:
        load_layout(data)  # InputError naming the field at fault
    except FacecastError:
        raise
    except (TypeError, ValueError, AttributeError, KeyError) as e:
        raise InputError(
            f"cannot read the layout ({type(e).__name__}: {str(e)[:200]})", where="layout"
        ) from None
    return data


def upload_layout(kind: str, text: str | None) -> dict | None:
    """The checked marker layout sent with an upload of input ``kind`` (its ``layout`` part, or None):
    a mocap take needs one, other kinds take none; InputError otherwise."""
    if text is not None:
        if kind != "markers":
            raise InputError(
                f"a layout goes with mocap input (.c3d/.trc/.csv), not {kind}", where="layout"
            )
        return parse_layout(text)
    if kind == "markers":
        raise InputError(
            "a mocap take needs its marker layout: send the layout file's content as a "
            "'layout' part (curl -F layout=@take.layout.json)",
            where="layout",
        )
    return None


#: OpenAPI schema of the ``layout`` form part of an upload.
LAYOUT_PART = {
    "type": "string",
    "format": "binary",
    "description": "mocap marker layout: the layout file's JSON content, as a file part or an "
    "inline field (required for .c3d/.trc/.csv); never a path",
}


def multipart_doc(**properties: dict) -> dict:
    """``openapi_extra`` of a route that reads a multipart/form-data body with a required ``file``
    part and the form parts ``properties`` (name: OpenAPI schema)."""
    return {
        "requestBody": {
            "required": True,
            "content": {
                "multipart/form-data": {
                    "schema": {"type": "object", "required": ["file"], "properties": properties}
                }
            },
        }
    }


def boundary_of(content_type: str) -> bytes:
    """The multipart boundary of a Content-Type header; InputError if it is not multipart/form-data."""
    ctype, opts = parse_options_header(content_type)
    if ctype != b"multipart/form-data" or not opts.get(b"boundary"):
        raise UnsupportedMedia(
            f"expected a multipart/form-data upload, got {content_type or 'no Content-Type'!r}; "
            "send the input file as a form part named 'file' (curl -F file=@take.fap)",
            where="Content-Type",
        )
    return opts[b"boundary"]


_FAP_HEADER = re.compile(rb"^\s*2\.1\s+\S+\s+[0-9.]+\s+[0-9]+\s*$")


def sniff_suffix(head: bytes) -> str | None:
    """The input suffix the first bytes of a file suggest (``.wav``, ``.fap``...), or None."""
    if head[:4] == b"RIFF" and head[8:12] == b"WAVE":
        return ".wav"
    if head[:4] == b"fLaC":
        return ".flac"
    if head[:4] == b"OggS":
        return ".ogg"
    if len(head) >= 2 and head[1] == 0x50 and 1 <= head[0] < 32:  # parameter block, 0x50 key
        return ".c3d"
    if head.lstrip().startswith(b"PathFileType"):
        return ".trc"
    if head.lstrip().startswith((b"<?xml", b"<bml")):
        return ".bml"
    for line in head.splitlines():
        if not line.strip() or line.lstrip().startswith(b"#"):
            continue
        if _FAP_HEADER.match(line):
            return ".fap"
        if line.count(b",") >= 3:
            return ".csv"
        break
    return None


def input_suffix(filename: str | None, head: bytes) -> str:
    """The input type of an upload: its file name's suffix if known, else what its content looks like."""
    name = safe_display_name(filename, "")
    suffix = ("." + name.rsplit(".", 1)[-1].lower()) if "." in name else ""
    if suffix in SUFFIXES:
        return suffix
    sniffed = sniff_suffix(head)
    if sniffed:
        return sniffed
    raise UnsupportedMedia(
        f"cannot tell what kind of input {name or 'the upload'!r} is; name the file with "
        f"one of {', '.join(sorted(SUFFIXES))}",
        where="file",
    )
