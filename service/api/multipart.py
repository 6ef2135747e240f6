"""A multipart/form-data request body, streamed into files of one directory.

    parts = await receive_parts(request, directory, fields={"scene": 1, "files": 64})

Starlette's form parser spools files above 1 MB into the system's temporary
directory; an upload must never write outside the data directory, so each
part goes straight into `directory` as it arrives, under a name the server
chooses (``part-0``, ``part-1``, ...; the client's file name is only data).
Unknown fields and more parts of a field than allowed stop the upload at
once. Parsing and writing run in a worker thread, chunk by chunk, so the
event loop never waits for the disk.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Mapping

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request

from ..errors import InvalidRequest, TooLarge

__all__ = ["Part", "receive_parts"]


@dataclass
class Part:
    """One part of the body: its field, the client's file name (None for a
    plain form field) and where its bytes are."""

    field: str
    filename: str | None
    path: Path
    size: int = 0


class _Writer:
    """python-multipart callbacks that write each part to its own file."""

    def __init__(self, directory: Path, fields: Mapping[str, int], too_many: Mapping[str, str]):
        self.directory, self.fields, self.too_many = directory, fields, too_many
        self.parts: list[Part] = []
        self.counts: dict[str, int] = {}
        self.ended = False
        self._header_name = b""
        self._header_value = b""
        self._disposition = b""
        self._file: BinaryIO | None = None

    def callbacks(self) -> dict:
        return {"on_part_begin": self.on_part_begin, "on_header_field": self.on_header_field,
                "on_header_value": self.on_header_value, "on_header_end": self.on_header_end,
                "on_headers_finished": self.on_headers_finished, "on_part_data": self.on_part_data,
                "on_part_end": self.on_part_end, "on_end": self.on_end}

    def on_part_begin(self) -> None:
        self._disposition = b""

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def on_header_end(self) -> None:
        if self._header_name.lower() == b"content-disposition":
            self._disposition = self._header_value
        self._header_name = self._header_value = b""

    def on_headers_finished(self) -> None:
        _, options = parse_options_header(self._disposition)
        if b"name" not in options:
            raise InvalidRequest("form", "a part has no Content-Disposition name")
        field = options[b"name"].decode("utf-8", "replace")
        if field not in self.fields:
            raise InvalidRequest(field, f"unknown form field (allowed: {', '.join(self.fields)})")
        count = self.counts[field] = self.counts.get(field, 0) + 1
        if count > self.fields[field]:
            if field in self.too_many:
                raise TooLarge(self.too_many[field])
            raise InvalidRequest(field, f"sent {count} times; at most {self.fields[field]}")
        filename = options.get(b"filename")
        path = self.directory / f"part-{len(self.parts)}"
        self.parts.append(Part(field, None if filename is None
                               else filename.decode("utf-8", "replace"), path))
        self._file = open(path, "xb")

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        self._file.write(data[start:end])
        self.parts[-1].size += end - start

    def on_part_end(self) -> None:
        self.close()

    def on_end(self) -> None:
        self.ended = True

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


async def receive_parts(request: Request, directory: Path, fields: Mapping[str, int],
                        too_many: Mapping[str, str] | None = None) -> list[Part]:
    """Stream the request's multipart body into `directory`; `fields` maps each
    accepted field name to how many parts it may have. More than that is a
    `TooLarge` with the message in `too_many` (if given for the field), else an
    `InvalidRequest`; so is an unknown field or a body that is not multipart."""
    content_type, params = parse_options_header(request.headers.get("content-type", ""))
    if content_type != b"multipart/form-data" or b"boundary" not in params:
        first = next(iter(fields))
        raise InvalidRequest(first, f"send a multipart/form-data body (curl -F {first}=@file); "
                                    f"got Content-Type '{request.headers.get('content-type', '')}'")
    writer = _Writer(directory, fields, too_many or {})
    try:
        # The parser refuses a boundary it cannot use (longer than 256 bytes) as it is built.
        parser = MultipartParser(params[b"boundary"], writer.callbacks())
        async for chunk in request.stream():
            if chunk:
                await run_in_threadpool(parser.write, chunk)
        await run_in_threadpool(parser.finalize)
    except FormParserError as exc:
        raise InvalidRequest("form", f"malformed multipart body: {exc}") from None
    finally:
        writer.close()
    if not writer.ended:
        raise InvalidRequest("form", "the multipart body ends before its closing boundary")
    return writer.parts
