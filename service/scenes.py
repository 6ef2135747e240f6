"""Scene use cases: the built-in scenes (by name) and uploaded ones (by content
hash): upload, list, look up, delete, find a thumbnail. Plain Python, no HTTP.

    with store.upload_dir() as directory:
        ...  # the HTTP layer writes the request's files into `directory`
        info, created = add_upload(sessions, store, scene_file, mesh_files, directory, now)

An upload is a scene JSON file and the Wavefront `.obj` files its mesh shapes
name by `"file"` (base names only). It is resolved like any scene, with mesh
files read only from the upload's private directory; the resolved document is
self-contained, so it is stored by its hash and nothing else is kept.

Resolving and storing run in a child process (`check_upload`): parsing a
large `.obj` and writing its canonical JSON is pure Python, tens of seconds
of one core for a 59 MiB mesh, and in the service's own process it held the
GIL from the event loop and every request thread (GET /jobs went from 7 ms
to seconds with three such uploads: docs/operations.md). The child is forked
from the forkserver that has this module imported, so it starts in
milliseconds, and the memory of the parsed mesh goes with it. `UploadSlots`
bounds the uploads received and checked at once (429 with Retry-After above).

Uploads are shared by content hash but owned by claim: each user who uploaded
a scene holds a claim on it (`SceneClaim`) and sees it; nobody else does
(admins and viewers see every upload). Deleting an upload removes the
caller's claim; the record goes with the last claim.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import posixpath
import signal
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from functools import cache
from pathlib import Path, PurePosixPath
from typing import Iterator

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from renderer import SceneError, builtin_scene_names, resolve_document, scene_text
from renderer.scene import triangle_count
from renderer.scene_format import ResolvedDocument

from .access import Principal, require_submit
from .errors import (Conflict, Forbidden, InvalidRequest, NotFound, RateLimited, ResultNotReady,
                     TooLarge)
from .models import SceneClaim, SceneRecord
from .store import Store
from .text import lone_surrogate

__all__ = ["SceneInfo", "UploadedFile", "UploadSlots", "MESH_SUFFIX", "add_upload",
           "check_upload", "resolve_upload", "list_scenes", "get_scene", "delete_scene",
           "uploaded_document", "thumbnail_file", "scene_hashes", "unknown_scene_hint"]

MESH_SUFFIX = ".obj"
MAX_NAME = 255  # bytes of a file name on common filesystems
# Retry-After of an upload refused while `UploadSlots` are full: a hint (a
# large upload takes tens of seconds, a small one milliseconds).
UPLOADS_BUSY_RETRY_AFTER = 5.0
# The CPU priority of an upload's check (nice): below the service's requests
# and scheduler, above the thumbnails (19).
CHECK_NICENESS = 10


@dataclass(frozen=True)
class UploadedFile:
    """A file of an upload request, already written to the upload's private
    directory at `path` (a name the server chose). `filename` is the client's
    name for it; `field` and `index` say where in the request it came."""

    field: str
    index: int
    filename: str
    path: Path

    @property
    def where(self) -> str:
        """The request field, as error messages name it: ``scene``, ``files[2]``."""
        return f"{self.field}[{self.index}]" if self.field == "files" else self.field


@dataclass(frozen=True)
class SceneInfo:
    """What the farm shows of a scene, built-in or uploaded."""

    id: str  # a built-in's name, or an upload's hash
    kind: str  # "builtin" | "uploaded"
    name: str
    description: str
    width: int
    height: int
    triangles: int
    scene_hash: str
    bytes: int
    created: datetime | None

    @classmethod
    def from_record(cls, record: SceneRecord) -> "SceneInfo":
        return cls(id=record.id, kind="uploaded", name=record.name,
                   description=record.description, width=record.width, height=record.height,
                   triangles=record.triangles, scene_hash=record.id, bytes=record.bytes,
                   created=record.created)


@cache
def _builtins() -> dict[str, tuple[SceneInfo, str]]:
    """Built-in scenes by name: (info, canonical text). Package data: read once."""
    out = {}
    for name in builtin_scene_names():
        doc = resolve_document(name, allow_files=False)
        key, text = scene_text(doc)
        camera = doc["camera"]
        out[name] = (SceneInfo(id=name, kind="builtin", name=name,
                               description=doc.get("description", ""), width=camera["width"],
                               height=camera["height"], triangles=triangle_count(doc),
                               scene_hash=key, bytes=len(text.encode()), created=None), text)
    return out


def unknown_scene_hint() -> str:
    """How a scene is named, for messages about an unknown one."""
    return (f"allowed: {', '.join(builtin_scene_names())}; an uploaded scene is named by its id "
            "(POST /scenes answers it, GET /scenes lists them)")


# -- reading --------------------------------------------------------------------------

def _visible_uploads(actor: Principal):
    """SELECT of the upload records `actor` may see."""
    query = select(SceneRecord)
    if not actor.sees_everything:
        query = query.join(SceneClaim, SceneClaim.scene_id == SceneRecord.id).where(
            SceneClaim.owner == actor.user)
    return query


def _visible_upload(session: Session, actor: Principal, scene_id: str) -> SceneRecord | None:
    return session.scalars(_visible_uploads(actor).where(SceneRecord.id == scene_id)).first()


def list_scenes(session: Session, actor: Principal) -> list[SceneInfo]:
    """Built-in scenes by name, then the uploads `actor` may see, newest first."""
    uploads = session.scalars(_visible_uploads(actor).order_by(SceneRecord.created.desc(),
                                                               SceneRecord.id))
    return [info for info, _ in _builtins().values()] + [SceneInfo.from_record(r) for r in uploads]


def get_scene(session: Session, actor: Principal, scene_id: str) -> SceneInfo:
    builtin = _builtins().get(scene_id)
    if builtin is not None:
        return builtin[0]
    record = _visible_upload(session, actor, scene_id)
    if record is None:
        raise NotFound(f"no scene '{scene_id}' ({unknown_scene_hint()})")
    return SceneInfo.from_record(record)


def uploaded_document(session: Session, store: Store, actor: Principal, scene_id: str,
                      whole: bool = True) -> tuple[dict, str] | None:
    """(resolved document, name) of the uploaded scene `scene_id`, or None
    (also when it is not the caller's to use). With `whole` false the document
    holds only its camera's width and height, from the record: parsing a large
    mesh's stored text holds the GIL for seconds (5 s for a 59 MiB .obj)."""
    record = _visible_upload(session, actor, scene_id)
    if record is None:
        return None
    if not whole:
        return {"camera": {"width": record.width, "height": record.height}}, record.name
    return ResolvedDocument(json.loads(store.scene_text(record.id)), store.asset_bytes), record.name


def thumbnail_file(session: Session, store: Store, actor: Principal, scene_id: str) -> Path:
    """The scene's thumbnail PNG; `ResultNotReady` until the service rendered it."""
    info = get_scene(session, actor, scene_id)
    path = store.thumbnail_path(info.scene_hash)
    if not path.is_file():
        raise ResultNotReady(f"scene '{scene_id}' has no thumbnail yet; it is rendered in the "
                             "background after the upload (or the service's start)")
    return path


def scene_hashes(sessions: sessionmaker[Session], store: Store) -> list[str]:
    """Hashes of every scene that should have a thumbnail (built-ins first); puts
    the built-ins' texts in the store so they can be read back by hash."""
    hashes = []
    for info, text in _builtins().values():
        store.put_scene(info.scene_hash, text)
        hashes.append(info.scene_hash)
    with sessions() as session:
        hashes += list(session.scalars(select(SceneRecord.id).order_by(SceneRecord.created)))
    return hashes


# -- changing -----------------------------------------------------------------------------

def delete_scene(session: Session, actor: Principal, scene_id: str) -> None:
    """Remove the caller's claim on an uploaded scene (an admin without one
    removes every claim); the record goes with the last claim. Its text stays
    in the store, so jobs that were submitted with it keep running."""
    if scene_id in _builtins():
        raise Conflict(f"scene '{scene_id}' is built in; only uploaded scenes can be deleted")
    record = _visible_upload(session, actor, scene_id)
    if record is None:
        raise NotFound(f"no scene '{scene_id}' ({unknown_scene_hint()})")
    if actor.role == "viewer":
        raise Forbidden(f"user '{actor.user}' is a viewer: it can read, not delete, scenes")
    claims = list(session.scalars(select(SceneClaim).where(SceneClaim.scene_id == scene_id)))
    mine = [c for c in claims if c.owner == actor.user]
    for claim in mine or claims:  # an admin without a claim of its own removes them all
        session.delete(claim)
    session.flush()
    if len(mine or claims) == len(claims):
        session.delete(record)


class UploadSlots:
    """At most `limit` uploads received and checked at once, in this process:

        with slots.hold():        # or RateLimited (429, Retry-After)
            ...                   # receive the body, check_upload
    """

    def __init__(self, limit: int):
        self.limit = limit
        self._free = threading.BoundedSemaphore(limit)

    @contextmanager
    def hold(self) -> Iterator[None]:
        if not self._free.acquire(blocking=False):
            raise RateLimited(f"{self.limit} scene uploads are being received and checked right "
                              "now, the most at once (RAYFARM_MAX_CONCURRENT_UPLOADS); retry "
                              f"in {UPLOADS_BUSY_RETRY_AFTER:g} s",
                              retry_after=UPLOADS_BUSY_RETRY_AFTER)
        try:
            yield
        finally:
            self._free.release()


def _store_upload(store: Store, scene: UploadedFile, files: list[UploadedFile],
                  directory: Path) -> dict:
    """Resolve an upload and store its canonical text: the record's fields."""
    doc, stem = resolve_upload(scene, files, directory)
    key, text = scene_text(doc)
    store.put_assets(doc.assets)  # before the text: a stored scene finds its assets
    store.put_scene(key, text)
    camera = doc["camera"]
    return dict(id=key, name=(doc["name"] or stem)[:200], description=doc["description"],
                triangles=triangle_count(doc), width=camera["width"], height=camera["height"],
                bytes=len(text.encode()))


def _check_in_child(sending, store: Store, scene: UploadedFile, files: list[UploadedFile],
                    directory: Path) -> None:
    """The child process of `check_upload`: send ("ok", fields) or the refusal."""
    try:  # the service's requests and scheduler come first
        os.nice(CHECK_NICENESS)
    except OSError:
        pass
    try:
        sending.send(("ok", _store_upload(store, scene, files, directory)))
    except InvalidRequest as exc:
        sending.send(("invalid", (exc.field, exc.message, exc.source)))
    except SceneError as exc:
        sending.send(("scene", (exc.message, exc.location)))
    except TooLarge as exc:
        sending.send(("large", (str(exc),)))
    except MemoryError:
        sending.send(("large", ("the upload is too large to check (out of memory)",)))
    sending.close()


def check_upload(store: Store, scene: UploadedFile, files: list[UploadedFile],
                 directory: Path) -> dict:
    """Resolve an upload and store its canonical text by hash, in a child
    process (see the module doc); returns the `SceneRecord` fields but
    `created`. Raises what `resolve_upload` raises. Blocks the calling thread
    (not the GIL) until the child is done."""
    context = multiprocessing.get_context("forkserver")
    receiving, sending = context.Pipe(duplex=False)
    child = context.Process(target=_check_in_child, name="rayfarm-upload-check", daemon=True,
                            args=(sending, store, scene, files, directory))
    child.start()
    sending.close()  # the child holds the only sending end: EOF if it dies
    try:
        try:
            kind, payload = receiving.recv()
        except EOFError:
            kind, payload = "died", None
    finally:
        receiving.close()
        child.join(30)
        if child.is_alive():
            child.kill()
            child.join()
    if kind == "ok":
        return payload
    if kind == "invalid":
        raise InvalidRequest(*payload)
    if kind == "scene":
        raise SceneError(*payload)
    if kind == "large":
        raise TooLarge(*payload)
    code = child.exitcode
    how = (f"signal {signal.Signals(-code).name}" if code is not None and code < 0
           else f"exit code {code}")
    # Killed (the kernel's OOM killer) or crashed on this input: the upload's
    # fault as far as anyone can tell, never a server error.
    raise TooLarge(f"the upload could not be checked: its checking process ended with {how}")


def add_upload(sessions: sessionmaker[Session], store: Store, actor: Principal,
               scene: UploadedFile, files: list[UploadedFile], directory: Path, now: datetime
               ) -> tuple[SceneInfo, bool]:
    """Resolve an upload (in a child process: `check_upload`), store it by
    hash, record it and the caller's claim. Returns (info, created): content
    this caller uploaded before answers its existing record, not created
    (someone else's identical upload is shared, and is new to this caller).

    Raises `InvalidRequest` (naming the field: ``files[1]``) or `SceneError`
    (naming the location in the scene: ``shapes[0].file``).
    """
    require_submit(actor)
    fields = check_upload(store, scene, files, directory)
    key = fields["id"]
    record = SceneRecord(created=now, **fields)
    for _ in range(3):  # the same content uploaded at the same moment: one record
        try:
            with sessions.begin() as session:
                existing = session.get(SceneRecord, key)
                if existing is None:
                    session.add(record)
                    session.flush()
                    existing = record
                claimed = session.get(SceneClaim, (key, actor.user)) is not None
                if not claimed:
                    session.add(SceneClaim(scene_id=key, owner=actor.user, created=now))
                return SceneInfo.from_record(existing), not claimed
        except IntegrityError:
            record = SceneRecord(**{c.name: getattr(record, c.name)
                                    for c in SceneRecord.__table__.columns})
    raise Conflict(f"scene {key} is being uploaded by someone else right now; try again")


def resolve_upload(scene: UploadedFile, files: list[UploadedFile],
                   directory: Path) -> tuple[dict, str]:
    """The resolved document of an upload and the scene file's stem (the name
    when the document has none). Mesh files are moved, under their checked
    names, into a new directory inside `directory`, the only place the scene
    may read them from."""
    by_name = _check_file_names(files)
    doc = _parse_scene_file(scene)
    used = _check_references(doc, by_name)
    for upload in files:
        if upload.filename not in used:
            raise InvalidRequest(upload.where, f"'{upload.filename}' is not named by any mesh "
                                 f"shape's \"file\" (named: {', '.join(sorted(used)) or 'none'}); "
                                 "send only the mesh files the scene uses")
    mesh_dir = directory / "meshes"
    mesh_dir.mkdir(mode=0o700)
    for name, upload in by_name.items():
        os.replace(upload.path, mesh_dir / name)
    try:
        resolved = resolve_document(doc, base_dir=mesh_dir)
    except SceneError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError, RecursionError) as exc:
        # What the validator did not anticipate is still the client's error.
        raise SceneError(f"malformed scene document ({type(exc).__name__}: {exc})") from None
    stem = PurePosixPath(scene.filename.replace("\\", "/")).stem if scene.filename else ""
    return resolved, stem or "uploaded"


def _check_file_names(files: list[UploadedFile]) -> dict[str, UploadedFile]:
    """Mesh files by name; each name a plain base name ending in .obj, once."""
    by_name: dict[str, UploadedFile] = {}
    for upload in files:
        name = upload.filename
        if not name:
            raise InvalidRequest(upload.where, "a mesh file needs a file name "
                                 "(the base name its scene's \"file\" uses)")
        if ("/" in name or "\\" in name or name in (".", "..")
                or any(ord(c) < 32 or c == "\x7f" for c in name)):
            raise InvalidRequest(upload.where, f"file name {name!r} must be a plain base name "
                                 "(no path separators, no '..', no control characters)")
        if len(name.encode()) > MAX_NAME:
            raise InvalidRequest(upload.where, f"file name longer than {MAX_NAME} bytes")
        if PurePosixPath(name).suffix.lower() != MESH_SUFFIX:
            raise InvalidRequest(upload.where, f"'{name}' is not a Wavefront {MESH_SUFFIX} file "
                                 f"(mesh files must end in {MESH_SUFFIX})")
        if name in by_name:
            raise InvalidRequest(upload.where, f"'{name}' is uploaded twice "
                                 f"(also as {by_name[name].where})")
        by_name[name] = upload
    return by_name


def _parse_scene_file(scene: UploadedFile) -> dict:
    """The scene file's JSON object; errors name the line and column."""
    name = scene.filename or "the scene file"
    data = scene.path.read_bytes()
    if not data.strip():
        raise SceneError(f"{name} is empty")
    try:
        text = data.decode("utf-8-sig")  # a byte-order mark is harmless
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        column = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        raise SceneError(f"{name} is not UTF-8 text: byte 0x{data[exc.start]:02x} at line "
                         f"{line}, column {column}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SceneError(f"invalid JSON in {name} at line {exc.lineno}, column {exc.colno}: "
                         f"{exc.msg}") from None
    except RecursionError:
        raise SceneError(f"{name} is nested too deeply") from None
    if not isinstance(doc, dict):  # a string would name a built-in scene or a path
        raise SceneError(f"a scene document must be a JSON object, {name} holds "
                         f"{type(doc).__name__ if doc is not None else 'null'}")
    found = lone_surrogate(doc)
    if found is not None:
        raise SceneError(f'not valid Unicode text in {name}: "{found[1][:60]}" holds a lone '
                         "surrogate (half of a UTF-16 pair)", found[0])
    return doc


def _check_references(doc: dict, by_name: dict[str, UploadedFile]) -> set[str]:
    """Names of the uploaded files the mesh shapes use; a `"file"` that names
    none of them is a SceneError at ``shapes[i].file``."""
    used: set[str] = set()
    shapes = doc.get("shapes")
    if not isinstance(shapes, list):
        return used  # the resolver reports it
    for i, shape in enumerate(shapes):
        if not (isinstance(shape, dict) and shape.get("type") == "mesh" and "file" in shape):
            continue
        loc = f"shapes[{i}].file"
        ref = shape["file"]
        if not isinstance(ref, str):
            raise SceneError("expected a file name (a string)", loc)
        name = posixpath.normpath(ref) if ref else ref
        if name not in by_name:
            uploaded = ", ".join(by_name) or "none"
            hint = ("; an upload names mesh files by their base name: "
                    f"\"file\": \"{posixpath.basename(ref)}\""
                    if posixpath.basename(ref) in by_name else
                    "; send it as a files part (-F files=@mesh.obj)")
            raise SceneError(f"mesh file '{ref}' was not uploaded (uploaded: {uploaded}){hint}",
                             loc)
        used.add(name)
    return used
