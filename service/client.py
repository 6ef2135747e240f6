"""A Python client of the rayfarm HTTP API (sync, on httpx).

    with RayfarmClient("http://127.0.0.1:8000", token="rf_...") as farm:
        job = farm.submit(scene="cornell-box", method="path", spp=64, depth=5)
        for kind, data in farm.events(job["id"]):     # job, units, unit, preview, ..., end
            print(kind)
        farm.download_result(job["id"], "cornell.exr")

It talks HTTP only: it imports neither the service nor the renderer (the
standard library and httpx are all it needs), so this one file can be
shipped alone.

Every request carries `Authorization: Bearer <token>`: the `token` given, else
`$RAYFARM_TOKEN`, else the first line of the file `$RAYFARM_TOKEN_FILE`, else
`$RAYFARM_DATA_DIR/admin.token` (default `./rayfarm-data/admin.token`: the
token the embedded service made for its admin on this machine).

Every refusal is a `ClientError`:

    ClientError              anything the client could not do
     ├── ServerUnavailable   no answer: connection refused, unknown host, timed
     │                       out, or an event stream lost and not regained
     ├── ServerError         the service failed (5xx) or did not answer like rayfarm
     ├── NotSupported        this service lacks the endpoint (an older version)
     ├── Unauthorized        401: no token, or a wrong, expired or revoked one
     ├── Forbidden           403: the token's role may not do this
     ├── RateLimited         429: too many requests; `.retry_after` seconds
     ├── NotFound            404: no such job, or its image is not there yet
     ├── Conflict            409: the request contradicts the job's state
     └── Invalid             422, or a local scene file that cannot be sent:
                             `.field` and `.message` of each error in `.errors`

Their messages are sentences a person can act on; `status_code` is the HTTP
status where there was one.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator
from urllib.parse import quote

import httpx

__all__ = ["RayfarmClient", "DEFAULT_SERVER", "ServerSentEvent", "parse_sse", "mesh_files",
           "scene_files", "zip_folder",
           "ClientError", "ServerUnavailable", "ServerError", "NotSupported", "NotFound",
           "Conflict", "Invalid", "Unauthorized", "Forbidden", "RateLimited", "FINAL_STATUSES",
           "find_token"]

DEFAULT_SERVER = "http://127.0.0.1:8000"
FINAL_STATUSES = ("done", "failed", "canceled")
STREAM_READ_TIMEOUT = 60.0  # the service sends a keep-alive comment every 15 s
_RETRY_CAP = 30.0  # never sleep longer than this before reconnecting, whatever `retry:` says
_USER_AGENT = "rayfarm-client/0.1"


# -- errors --------------------------------------------------------------------------

class ClientError(Exception):
    """Anything the client could not do; `status_code` is the HTTP status, if any."""

    def __init__(self, message: str, status_code: int | None = None):
        super().__init__(message)
        self.status_code = status_code


class ServerUnavailable(ClientError):
    pass


class ServerError(ClientError):
    pass


class NotSupported(ClientError):
    pass


class NotFound(ClientError):
    pass


class Unauthorized(ClientError):
    pass


class Forbidden(ClientError):
    pass


class RateLimited(ClientError):
    def __init__(self, message: str, status_code: int | None = None, retry_after: float = 1.0):
        super().__init__(message, status_code)
        self.retry_after = retry_after


class Conflict(ClientError):
    pass


class Invalid(ClientError):
    """A refused field: `field` (dotted, e.g. `spp` or `scene.shapes[0].file`) and
    `message` of the first error; `errors` holds every (field, message) pair."""

    def __init__(self, errors: list[tuple[str, str]], status_code: int | None = None):
        self.errors = errors or [("request", "invalid")]
        self.field, self.message = self.errors[0]
        super().__init__("; ".join(f"{f}: {m}" for f, m in self.errors), status_code)

    @classmethod
    def from_detail(cls, detail: Any, status_code: int = 422) -> "Invalid":
        """From FastAPI's 422 body: `[{"loc": ["body", "spp"], "msg": "spp: ...", ...}]`."""
        if not isinstance(detail, list):
            return cls([("request", str(detail))], status_code)
        errors = []
        for item in detail:
            loc = list(item.get("loc") or []) if isinstance(item, dict) else []
            if loc and loc[0] in ("body", "query", "path", "header"):
                loc = loc[1:]
            field = ""
            for part in loc:  # ["shapes", 0, "file"] -> shapes[0].file
                if isinstance(part, int):
                    field += f"[{part}]"
                else:
                    field += f".{part}" if field else str(part)
            field = field or "request"
            message = str(item.get("msg", item)) if isinstance(item, dict) else str(item)
            if message.startswith(f"{field}: "):  # the service's messages name the field already
                message = message[len(field) + 2:]
            errors.append((field, message))
        return cls(errors, status_code)


def _detail(response: httpx.Response) -> Any:
    try:
        body = response.json()
    except ValueError:
        return response.text.strip()[:300] or response.reason_phrase
    return body.get("detail", body) if isinstance(body, dict) else body


def _raise_for(response: httpx.Response) -> None:
    """Raise the `ClientError` that a non-2xx answer means."""
    if response.is_success:
        return
    code = response.status_code
    detail = _detail(response)
    request = f"{response.request.method} {response.request.url.path}"
    if code == 422:
        raise Invalid.from_detail(detail, code)
    text = detail if isinstance(detail, str) else json.dumps(detail)
    if code == 404:
        if text == "Not Found":  # the router's answer: no such endpoint
            raise NotFound(f"{request}: no such endpoint at {response.request.url.host}; "
                           "is this a rayfarm service?", code)
        raise NotFound(text, code)
    if code == 409:
        raise Conflict(text, code)
    if code == 401:
        raise Unauthorized(f"{text} (set RAYFARM_TOKEN, or pass --token)", code)
    if code == 403:
        raise Forbidden(text, code)
    if code == 429:
        try:
            retry_after = float(response.headers.get("retry-after", "1"))
        except ValueError:
            retry_after = 1.0
        raise RateLimited(f"{text} (retry after {retry_after:g} s)", code, retry_after)
    if code >= 500:
        raise ServerError(f"the service failed on {request} ({code}): {text}", code)
    raise ClientError(f"{request} answered {code}: {text}", code)


# -- server-sent events ----------------------------------------------------------------

@dataclass(frozen=True)
class ServerSentEvent:
    """One dispatched event: its type (`message` unless named), data, last id, retry (ms)."""

    event: str
    data: str
    id: str | None = None
    retry: int | None = None


def parse_sse(lines: Iterable[str]) -> Iterator[ServerSentEvent | int]:
    """Decode `text/event-stream` lines (already split at CR, LF or CRLF) into
    events, following the WHATWG rules: `data` lines join with newlines; a
    blank line dispatches; an event without data is dropped; `:` starts a
    comment; one space after the colon is removed; unknown fields are ignored.
    A `retry:` line is yielded as its int (milliseconds) when it arrives.

        list(parse_sse(["event: job", "data: {", "data: }", ""]))
        -> [ServerSentEvent(event='job', data='{\\n}', id=None, retry=None)]
    """
    kind, data, last_id = "", [], None
    for line in lines:
        if line == "":
            if data:
                yield ServerSentEvent(kind or "message", "\n".join(data), last_id)
            kind, data = "", []
            continue
        if line.startswith(":"):
            continue  # a comment: keep-alive
        name, colon, value = line.partition(":")
        if colon and value.startswith(" "):
            value = value[1:]
        if name == "event":
            kind = value
        elif name == "data":
            data.append(value)
        elif name == "id":
            if "\0" not in value:
                last_id = value
        elif name == "retry":
            if value.isascii() and value.isdigit():
                yield int(value)
    # A stream that ends without a blank line drops its unfinished event (as browsers do).


# -- scene files -------------------------------------------------------------------------

SCENE_SUFFIXES = (".json", ".xml", ".gltf", ".glb")
ARCHIVE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tbz2", ".tar.xz", ".txz")
# What a folder sent as one zip may hold: the service's default limits
# (RAYFARM_MAX_UPLOAD_FILES, RAYFARM_MAX_UPLOAD_UNPACKED_BYTES); a folder
# past them is refused here, before it is read, with a message saying why.
MAX_FOLDER_FILES = 4096
MAX_FOLDER_BYTES = 1 << 30
# Files already compressed are stored in the zip as they are.
_STORED = (".png", ".jpg", ".jpeg", ".exr", ".glb", ".zip", ".gz", ".tgz", ".bz2", ".xz",
           ".serialized")


def scene_files(doc: dict, scene_dir: Path) -> list[tuple[str, Path]]:
    """The files a JSON scene document names by `"file"` (a mesh shape's, a
    texture's: at any depth), as (path relative to `scene_dir`, the file);
    each must lie inside `scene_dir`. Raises `Invalid` for a missing file."""
    found: dict[str, Path] = {}
    base = scene_dir.resolve()

    def visit(node, where: str) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                field = f"{where}.{key}" if where else str(key)
                if key == "file" and isinstance(value, str):
                    add(value, field)
                else:
                    visit(value, field)
        elif isinstance(node, list):
            for i, item in enumerate(node):
                visit(item, f"{where}[{i}]")

    def add(ref: str, field: str) -> None:
        path = (base / ref).resolve()
        if base not in path.parents:
            raise Invalid([(f"scene.{field}", f"{ref} lies outside the scene's directory {base}")])
        if not path.is_file():
            raise Invalid([(f"scene.{field}", f"file not found: {path}")])
        found[path.relative_to(base).as_posix()] = path

    visit(doc, "")
    return sorted(found.items())


def mesh_files(doc: dict, scene_dir: Path) -> list[Path]:
    """The files a JSON scene document names (see `scene_files`)."""
    return [path for _, path in scene_files(doc, scene_dir)]


def _zip_root(folder: Path) -> str:
    """The folder's name, as zip_folder puts it above every file."""
    return Path(folder).resolve().name.lstrip(".") or "scene"


def zip_folder(folder: Path, out) -> int:
    """Write the folder's files (hidden ones left out; symbolic links to files
    followed, to folders not) as a zip into the binary file `out`, each under
    the folder's name (`veach-bidir/scene.xml`) as `zip -r veach-bidir.zip
    veach-bidir` packs it: an importer that names a scene after its folder
    then names it alike either way. Returns how many files. Raises `Invalid`
    for a folder past MAX_FOLDER_FILES or MAX_FOLDER_BYTES, before any is read."""
    import zipfile

    folder = Path(folder)
    root = _zip_root(folder)
    files: list[tuple[str, Path]] = []
    total = 0
    for directory, subdirs, names in os.walk(folder):
        subdirs[:] = sorted(d for d in subdirs if not d.startswith("."))
        for name in sorted(names):
            path = Path(directory) / name
            if name.startswith(".") or not path.is_file():
                continue
            files.append((path.relative_to(folder).as_posix(), path))
            total += path.stat().st_size
            if len(files) > MAX_FOLDER_FILES or total > MAX_FOLDER_BYTES:
                raise Invalid([("scene", f"{folder} holds more than {MAX_FOLDER_FILES} files or "
                                         f"{MAX_FOLDER_BYTES >> 20} MiB, past what the service "
                                         "takes by default: upload a folder holding only the "
                                         "scene and its files")])
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, path in files:
            kind = zipfile.ZIP_STORED if name.lower().endswith(_STORED) else zipfile.ZIP_DEFLATED
            archive.write(path, f"{root}/{name}", compress_type=kind)
    return len(files)


def _read_file(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise Invalid([("scene", f"cannot read {path}: {exc.strerror or exc}")]) from None


def _read_scene(path: Path) -> tuple[bytes, dict]:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise Invalid([("scene", f"cannot read {path}: {exc.strerror or exc}")]) from None
    try:
        doc = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        raise Invalid([("scene", f"{path} is not a JSON scene document ({exc})")]) from None
    if not isinstance(doc, dict):
        raise Invalid([("scene", f"{path} holds a JSON {type(doc).__name__}, not a scene object")])
    return raw, doc


# -- the client ------------------------------------------------------------------------------

def find_token() -> str | None:
    """The token from the environment (see the module doc), or None."""
    token = os.environ.get("RAYFARM_TOKEN", "").strip()
    if token:
        return token
    data_dir = Path(os.environ.get("RAYFARM_DATA_DIR") or "rayfarm-data")
    for path in (os.environ.get("RAYFARM_TOKEN_FILE"), data_dir / "admin.token"):
        if not path:
            continue
        try:
            lines = Path(path).read_text().split()
        except OSError:
            continue
        if lines:
            return lines[0]
    return None


def normalize_url(url: str) -> str:
    """`localhost:8000` -> `http://localhost:8000`; no trailing slash."""
    url = url.strip().rstrip("/")
    return url if "://" in url else f"http://{url}"


class RayfarmClient:
    """The rayfarm HTTP API as methods; JSON answers come back as dicts.

        with RayfarmClient("http://farm:8000", timeout=30) as farm:
            job_id = farm.submit(scene="cornell-box", method="path", spp=16, depth=5)["id"]
            job = farm.wait(job_id)                  # the final job (done, failed or canceled)
    """

    def __init__(self, base_url: str = DEFAULT_SERVER, timeout: float = 30.0,
                 token: str | None = None):
        self.base_url = normalize_url(base_url)
        self.timeout = timeout
        token = token or find_token()
        headers = {"User-Agent": _USER_AGENT}
        if token:
            headers["Authorization"] = f"Bearer {token}"
        self._http = httpx.Client(base_url=self.base_url, timeout=timeout, headers=headers)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> "RayfarmClient":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"RayfarmClient({self.base_url!r})"

    # -- plumbing ----------------------------------------------------------------------
    def _unavailable(self, exc: httpx.TransportError, doing: str = "") -> ServerUnavailable:
        where = f"the rayfarm service at {self.base_url}"
        if isinstance(exc, httpx.ConnectError):
            reason = str(exc) or "connection failed"
            return ServerUnavailable(f"cannot reach {where} ({reason}); is `rayfarm serve` "
                                     "running there? (--server URL or RAYFARM_SERVER)")
        if isinstance(exc, httpx.TimeoutException):
            return ServerUnavailable(f"{where} did not answer {doing}in time "
                                     f"(timeout {self.timeout:g} s)")
        return ServerUnavailable(f"lost the connection to {where} {doing}"
                                 f"({type(exc).__name__}: {exc})")

    def _request(self, method: str, path: str, **kwargs) -> httpx.Response:
        try:
            response = self._http.request(method, path, **kwargs)
        except httpx.TransportError as exc:
            raise self._unavailable(exc) from None
        _raise_for(response)
        return response

    def _json(self, method: str, path: str, **kwargs) -> Any:
        return self._parse(self._request(method, path, **kwargs))

    def _parse(self, response: httpx.Response) -> Any:
        try:
            return response.json()
        except ValueError:
            raise ServerError(f"{response.request.method} {response.request.url.path} did not "
                              f"answer JSON; is {self.base_url} a rayfarm service?",
                              response.status_code) from None

    # -- jobs --------------------------------------------------------------------------
    def submit(self, **fields) -> dict:
        """POST /jobs: `scene` (a built-in name, an uploaded scene's id or a
        document), `method`, `spp`, `depth`, and optionally `tile_size`,
        `seed`, `sampler`, `width`, `height`, `options`, `priority`,
        `progressive`, `denoise`, `target` ({rel_error, max_spp, max_seconds}:
        render to a noise target; spp is then the ceiling). Fields that are None are left to the service's
        defaults. Returns the queued job."""
        return self._json("POST", "/jobs", json={k: v for k, v in fields.items() if v is not None})

    def job(self, job_id: str) -> dict:
        return self._json("GET", f"/jobs/{job_id}")

    def jobs(self, status: str | None = None, limit: int = 100, offset: int = 0,
             **filters: str) -> list[dict]:
        """Jobs, newest first; `status` and the filters `method`, `scene`,
        `sampler`, `owner` narrow them (an unknown filter is `Invalid`)."""
        params: dict[str, Any] = {"limit": limit, "offset": offset, **filters}
        if status is not None:
            params["status"] = status
        return self._json("GET", "/jobs", params=params)

    def units(self, job_id: str) -> list[dict]:
        return self._json("GET", f"/jobs/{job_id}/units")

    def unit_log(self, job_id: str, index: int) -> dict:
        """What unit `index`'s tasks logged: ``attempts``, one per task, each with
        ``lines``, ``traceback``, ``outcome``, ``worker``."""
        return self._json("GET", f"/jobs/{job_id}/units/{int(index)}/log")

    def set_priority(self, job_id: str, priority: int) -> dict:
        return self._json("PATCH", f"/jobs/{job_id}", json={"priority": priority})

    def cancel(self, job_id: str) -> dict:
        return self._json("POST", f"/jobs/{job_id}/cancel")

    def pause(self, job_id: str) -> dict:
        return self._json("POST", f"/jobs/{job_id}/pause")

    def resume(self, job_id: str) -> dict:
        return self._json("POST", f"/jobs/{job_id}/resume")

    def retry(self, job_id: str) -> dict:
        return self._json("POST", f"/jobs/{job_id}/retry")

    def requeue(self, job_id: str) -> dict:
        return self._json("POST", f"/jobs/{job_id}/requeue")

    def delete(self, job_id: str) -> None:
        self._request("DELETE", f"/jobs/{job_id}")

    # -- the estimator lab --------------------------------------------------------------
    def create_experiment(self, **fields) -> dict:
        """POST /experiments: `scene`, `configs` ([{method, sampler, options,
        label}]), `spp` (levels), and optionally `repeats`, `depth`, `width`,
        `height`, `block`, `seed`, `reference` ({job} or {method, spp}),
        `priority`. Returns the experiment (its jobs queued)."""
        return self._json("POST", "/experiments",
                          json={k: v for k, v in fields.items() if v is not None})

    def experiment(self, experiment_id: str) -> dict:
        return self._json("GET", f"/experiments/{experiment_id}")

    def experiments(self, limit: int = 100) -> list[dict]:
        return self._json("GET", "/experiments", params={"limit": limit})

    def experiment_csv(self, experiment_id: str) -> str:
        return self._request("GET", f"/experiments/{experiment_id}/report.csv").text

    def cancel_experiment(self, experiment_id: str) -> dict:
        return self._json("POST", f"/experiments/{experiment_id}/cancel")

    # -- images ------------------------------------------------------------------------
    def download_result(self, job_id: str, path: str | os.PathLike) -> Path:
        """Stream a done job's EXR to `path` (written whole or not at all)."""
        return self._download(f"/jobs/{job_id}/result.exr", Path(path))

    def download_preview(self, job_id: str, path: str | os.PathLike) -> Path:
        """The running (or final) tonemapped preview PNG."""
        return self._download(f"/jobs/{job_id}/preview.png", Path(path))

    def download_noise(self, job_id: str, path: str | os.PathLike) -> Path:
        """The noise heatmap PNG (relative standard error per pixel)."""
        return self._download(f"/jobs/{job_id}/noise.png", Path(path))

    def _download(self, url: str, path: Path) -> Path:
        # Into a temporary file beside the target, renamed at the end: a reader
        # never sees half an image, and a failed download leaves nothing behind.
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, part = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as out:
                try:
                    with self._http.stream("GET", url) as response:
                        if not response.is_success:
                            response.read()
                            _raise_for(response)
                        for chunk in response.iter_bytes():
                            out.write(chunk)
                except httpx.TransportError as exc:
                    raise self._unavailable(exc, f"while sending {url} ") from None
            # mkstemp makes the file private (0600); a downloaded image gets the
            # permissions any new file of this user would get.
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(part, 0o666 & ~umask)
            os.replace(part, path)
        except BaseException:
            Path(part).unlink(missing_ok=True)
            raise
        return path

    # -- events ------------------------------------------------------------------------
    def events(self, job_id: str) -> Iterator[tuple[str, Any]]:
        """Follow a job's server-sent events as (kind, data) pairs, data parsed
        from JSON: a snapshot (`job`, then `units` once planned), then `unit`,
        `job` and `preview` events, and last `end` ({"job_id", "status"});
        the iterator stops after `end`.

        A connection that drops (or ends without `end`) is re-opened once,
        after the delay the service asked for in its `retry:` line; the
        service then sends a fresh snapshot, so a `job` event follows. If the
        re-opened stream fails before delivering an event, `ServerUnavailable`;
        if the job was deleted meanwhile, `NotFound`.
        """
        retry = 2.0
        last_id: str | None = None
        reconnecting = False
        opened = False  # a first request that fails is plain unavailability, not a drop
        while True:
            headers = {"Accept": "text/event-stream", "Cache-Control": "no-cache"}
            if last_id is not None:
                headers["Last-Event-ID"] = last_id
            timeout = httpx.Timeout(self.timeout, read=max(self.timeout, STREAM_READ_TIMEOUT))
            try:
                with self._http.stream("GET", f"/jobs/{job_id}/events", headers=headers,
                                       timeout=timeout) as response:
                    if not response.is_success:
                        response.read()
                        _raise_for(response)
                    opened = True
                    for item in parse_sse(response.iter_lines()):
                        if isinstance(item, int):
                            retry = min(item / 1000.0, _RETRY_CAP)
                            continue
                        reconnecting = False  # this stream works: a later drop may reconnect
                        last_id = item.id
                        yield item.event, _decode(item.data)
                        if item.event == "end":
                            return
                lost: Exception | None = None  # ended without `end`: the service went away
            except httpx.TransportError as exc:
                if not opened:
                    raise self._unavailable(exc, "with the event stream ") from None
                lost = exc
            if reconnecting:
                reason = f"{type(lost).__name__}: {lost}" if lost else "closed without an end event"
                raise ServerUnavailable(f"lost the event stream of job {job_id} at {self.base_url} "
                                        f"twice in a row ({reason})")
            reconnecting = True
            time.sleep(retry)

    def wait(self, job_id: str) -> dict:
        """Follow the job's events until it is final; returns the final job
        (done, failed or canceled). A job deleted meanwhile raises `NotFound`."""
        for kind, data in self.events(job_id):
            if kind == "end":
                if isinstance(data, dict) and data.get("status") == "deleted":
                    raise NotFound(f"job '{job_id}' was deleted", 404)
                return self.job(job_id)
        raise ServerError(f"the event stream of job {job_id} ended without an end event")

    # -- scenes and the registries -------------------------------------------------------
    def upload_scene(self, path: str | os.PathLike, main: str | None = None) -> dict:
        """POST /scenes. `path` is a JSON scene file (sent with the files it
        names by `"file"`, at their paths relative to it), a Mitsuba .xml or a
        glTF file (sent with its whole folder, as a zip: the files an XML
        names are only known to its importer), a folder (zipped; `main`
        names its scene file where it holds several) or an archive (.zip,
        .tar, .tar.gz: sent as it is). Returns the stored scene's record, its
        import report included; its `id` is what a job's `scene` takes.
        `NotSupported` if the service takes no uploads; `Invalid` for an
        unreadable file."""
        path = Path(path)
        lowered = path.name.lower()
        with tempfile.TemporaryFile() as packed:
            form: dict[str, str] = {}
            if path.is_dir():
                zip_folder(path, packed)
                files = [("scene", (f"{path.name or 'scene'}.zip", packed, "application/zip"))]
                main = main and f"{_zip_root(path)}/{main}"  # `main` is relative to the folder
            elif lowered.endswith(ARCHIVE_SUFFIXES):
                files = [("scene", (path.name, _read_file(path), "application/octet-stream"))]
            elif lowered.endswith(".json"):
                raw, doc = _read_scene(path)
                files = [("scene", (path.name, raw, "application/json"))]
                files += [("files", (name, _read_file(file), "application/octet-stream"))
                          for name, file in scene_files(doc, path.parent)]
            elif lowered.endswith(SCENE_SUFFIXES):
                _read_file(path)  # a clear message for a file that is not there
                zip_folder(path.parent, packed)
                files = [("scene", (f"{path.parent.name or 'scene'}.zip", packed,
                                    "application/zip"))]
                main = f"{_zip_root(path.parent)}/{main or path.name}"
            else:
                raise Invalid([("scene", f"{path} is not a scene file ({', '.join(SCENE_SUFFIXES)}),"
                                         f" a folder or an archive ({', '.join(ARCHIVE_SUFFIXES)})")])
            if main is not None:
                form["main"] = main
            packed.seek(0)
            try:
                response = self._http.post("/scenes", files=files, data=form)
            except httpx.TransportError as exc:
                raise self._unavailable(exc, "while uploading the scene ") from None
        if response.status_code == 405 or (response.status_code == 404
                                           and _detail(response) == "Not Found"):
            raise NotSupported(f"the service at {self.base_url} takes no scene uploads "
                               "(POST /scenes); it predates them", response.status_code)
        _raise_for(response)
        return self._parse(response)

    def scene(self, scene_id: str) -> dict:
        """GET /scenes/{id}: one scene, its import report included."""
        return self._json("GET", f"/scenes/{_segment(scene_id)}")

    def scenes(self) -> list[dict]:
        return self._json("GET", "/scenes")

    def methods(self) -> list[dict]:
        return self._json("GET", "/methods")

    def samplers(self) -> list[dict]:
        return self._json("GET", "/samplers")

    def workers(self) -> list[dict]:
        return self._json("GET", "/workers")

    def disable_worker(self, name: str) -> dict:
        """Drain a worker (admins): it finishes its units and takes no new ones."""
        return self._json("POST", f"/workers/{_segment(name)}/disable")

    def enable_worker(self, name: str) -> dict:
        return self._json("POST", f"/workers/{_segment(name)}/enable")

    def remove_worker(self, name: str) -> None:
        """Forget a lost or offline worker (admins; `Conflict` for a live one)."""
        self._request("DELETE", f"/workers/{_segment(name)}")

    def blocklist(self, job_id: str) -> list[dict]:
        """The workers that failed units of the job; `blocked` set: blocklisted for it."""
        return self._json("GET", f"/jobs/{job_id}/blocklist")

    def clear_blocklist(self, job_id: str, worker: str) -> None:
        self._request("DELETE", f"/jobs/{job_id}/blocklist/{_segment(worker)}")

    def health(self) -> dict:
        """GET /healthz: the report, also when it says unhealthy (503)."""
        try:
            response = self._http.get("/healthz")
        except httpx.TransportError as exc:
            raise self._unavailable(exc) from None
        if response.status_code != 503:
            _raise_for(response)
        return self._parse(response)


def _segment(name: str) -> str:
    """A worker's name as one URL path segment (names look like rayfarm-12@host)."""
    return quote(name, safe="@")


def _decode(data: str) -> Any:
    try:
        return json.loads(data)
    except ValueError:
        return data
