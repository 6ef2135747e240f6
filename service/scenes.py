"""Scene use cases: the built-in scenes (by name) and uploaded ones (by content
hash): upload, list, look up, delete, find a thumbnail. Plain Python, no HTTP.

    with store.upload_dir() as directory:
        ...  # the HTTP layer writes the request's files into `directory`
        info, created = add_upload(sessions, store, actor, scene_file, files, directory, now,
                                   main=None, limits=UploadLimits.from_settings(settings))

An upload is a folder: a scene file (rayfarm JSON, Mitsuba XML, glTF) with
the files it names at their relative paths (`models/Mesh000.obj`), or one
archive (zip, tar) of the folder, or files alone (a browser's folder
picker); `service.upload_tree` lays it out in the upload's private
directory, with every hostile path and archive refused, and finds the main
scene file. The importer (`renderer.importers`) reads it, with every path
resolved inside that folder only, into a canonical document that names its
meshes and textures by digest, the assets themselves, and an import report
(what was not taken as written). The document is stored by its hash, the
assets by theirs, the report with the scene's record; the folder is deleted.

Importing and storing run in a child process (`check_upload`): unpacking an
archive and parsing a large mesh are tens of seconds of one core, and in
the service's own process they held the GIL from the event loop and every
request thread (GET /jobs went from 7 ms to seconds with three such uploads:
docs/operations.md). The child is forked from the forkserver that has this
module imported, so it starts in milliseconds, and the memory of the parsed
mesh goes with it. `UploadSlots` bounds the uploads received and checked at
once (429 with Retry-After above).

Uploads are shared by content hash but owned by claim: each user who uploaded
a scene holds a claim on it (`SceneClaim`) and sees it; nobody else does
(admins and viewers see every upload). Deleting an upload removes the
caller's claim; the record goes with the last claim.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from functools import cache
from pathlib import Path
from typing import Iterator

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from renderer import SceneError, builtin_scene_names, resolve_document, scene_text
from renderer.importers import import_scene, scene_name
from renderer.scene import triangle_count
from renderer.scene_format import ResolvedDocument
from renderer.spec import default_depth

from .access import Principal, require_submit
from .errors import (Conflict, Forbidden, InvalidRequest, NotFound, RateLimited, ResultNotReady,
                     TooLarge)
from .models import SceneClaim, SceneRecord
from .store import Store
from .text import lone_surrogate
from .upload_tree import (ARCHIVE_SUFFIXES, SCENE_SUFFIXES, UploadLimits, UploadTree,
                          archive_kind, scene_suffix)

__all__ = ["SceneInfo", "UploadedFile", "UploadSlots", "ImportedUpload", "add_upload",
           "check_upload", "import_upload", "list_scenes", "get_scene", "delete_scene",
           "uploaded_document", "thumbnail_file", "scene_hashes", "unknown_scene_hint"]

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
    source: str = ""  # an upload's main file, its path in the upload
    report: tuple[dict, ...] = ()  # the import report: {element, file, line, action}
    # A job's depth when it gives none (renderer.spec.default_depth); None for
    # an upload recorded before the ledger kept it (its jobs read the file).
    default_depth: int | None = None

    @classmethod
    def from_record(cls, record: SceneRecord) -> "SceneInfo":
        return cls(id=record.id, kind="uploaded", name=record.name,
                   description=record.description, width=record.width, height=record.height,
                   triangles=record.triangles, scene_hash=record.id, bytes=record.bytes,
                   created=record.created, source=record.source or "",
                   report=tuple(_stored_report(record.report)),
                   default_depth=record.default_depth)


def _stored_report(text: str | None) -> list[dict]:
    try:
        entries = json.loads(text or "[]")
    except ValueError:
        return []
    return [e for e in entries if isinstance(e, dict)] if isinstance(entries, list) else []


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
                               scene_hash=key, bytes=len(text.encode()), created=None,
                               default_depth=default_depth(doc)), text)
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
    holds only its camera's width and height and its default depth, from the
    record: parsing a large mesh's stored text holds the GIL for seconds (5 s
    for a 59 MiB .obj)."""
    record = _visible_upload(session, actor, scene_id)
    if record is None:
        return None
    if not whole and record.default_depth is not None:
        return {"camera": {"width": record.width, "height": record.height},
                "defaults": {"max_depth": record.default_depth},
                "triangles": record.triangles}, record.name
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


def _store_upload(store: Store, scene: UploadedFile | None, files: list[UploadedFile],
                  directory: Path, main: str | None, limits: UploadLimits) -> dict:
    """Import an upload and store its canonical text and assets: the record's fields."""
    imported = import_upload(scene, files, directory, main, limits)
    key, text = scene_text(imported.doc)
    store.put_assets(imported.assets)  # before the text: a stored scene finds its assets
    store.put_scene(key, text)
    doc = imported.doc
    camera = doc["camera"]
    return dict(id=key, name=(doc["name"] or imported.name)[:200], description=doc["description"],
                triangles=_triangles(imported), width=camera["width"], height=camera["height"],
                bytes=len(text.encode()), source=imported.source[:1024],
                report=json.dumps(imported.report), default_depth=default_depth(doc))


def _check_in_child(sending, store: Store, scene: UploadedFile | None,
                    files: list[UploadedFile], directory: Path, main: str | None,
                    limits: UploadLimits) -> None:
    """The child process of `check_upload`: send ("ok", fields) or the refusal."""
    try:  # the service's requests and scheduler come first
        os.nice(CHECK_NICENESS)
    except OSError:
        pass
    try:
        sending.send(("ok", _store_upload(store, scene, files, directory, main, limits)))
    except InvalidRequest as exc:
        sending.send(("invalid", (exc.field, exc.message, exc.source)))
    except SceneError as exc:
        sending.send(("scene", (exc.message, exc.location)))
    except TooLarge as exc:
        sending.send(("large", (str(exc),)))
    except MemoryError:
        sending.send(("large", ("the upload is too large to check (out of memory)",)))
    sending.close()


def check_upload(store: Store, scene: UploadedFile | None, files: list[UploadedFile],
                 directory: Path, main: str | None = None,
                 limits: UploadLimits = UploadLimits()) -> dict:
    """Import an upload and store its canonical text and assets by hash, in a
    child process (see the module doc); returns the `SceneRecord` fields but
    `created`. Raises what `import_upload` raises. Blocks the calling thread
    (not the GIL) until the child is done."""
    context = multiprocessing.get_context("forkserver")
    receiving, sending = context.Pipe(duplex=False)
    child = context.Process(target=_check_in_child, name="rayfarm-upload-check", daemon=True,
                            args=(sending, store, scene, files, directory, main, limits))
    child.start()
    sending.close()  # the child holds the only sending end: EOF if it dies
    kind, payload = "slow", None
    try:
        try:
            if receiving.poll(limits.max_seconds):
                kind, payload = receiving.recv()
            else:  # a file that makes an importer spin: its process is killed below
                kind, payload = "slow", None
        except EOFError:
            kind, payload = "died", None
    finally:
        receiving.close()
        child.join(30 if kind != "slow" else 0)
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
    if kind == "slow":
        raise TooLarge(f"the upload took more than {limits.max_seconds:g} s to check "
                       "(RAYFARM_UPLOAD_CHECK_SECONDS)")
    code = child.exitcode
    how = (f"signal {signal.Signals(-code).name}" if code is not None and code < 0
           else f"exit code {code}")
    # Killed (the kernel's OOM killer) or crashed on this input: the upload's
    # fault as far as anyone can tell, never a server error.
    raise TooLarge(f"the upload could not be checked: its checking process ended with {how}")


def add_upload(sessions: sessionmaker[Session], store: Store, actor: Principal,
               scene: UploadedFile | None, files: list[UploadedFile], directory: Path,
               now: datetime, main: str | None = None,
               limits: UploadLimits = UploadLimits()) -> tuple[SceneInfo, bool]:
    """Import an upload (in a child process: `check_upload`), store it by
    hash, record it and the caller's claim. Returns (info, created): content
    this caller uploaded before answers its existing record, not created
    (someone else's identical upload is shared, and is new to this caller).

    Raises `InvalidRequest` (naming the field: ``files[1]``, ``main``, or
    ``scene`` with the archive member), `TooLarge` (a limit of `limits`) or
    `SceneError` (naming the place in the scene: ``models/a.ply:12``).
    """
    require_submit(actor)
    fields = check_upload(store, scene, files, directory, main, limits)
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


@dataclass(frozen=True)
class ImportedUpload:
    """An upload imported: the resolved document, the assets it names (by
    digest), the import report (a list of {element, file, line, action}), the
    main file's path in the upload and the scene's name by
    `renderer.importers.scene_name` (a JSON document's own name comes first)."""

    doc: dict
    assets: dict[str, bytes]
    report: list[dict]
    source: str
    name: str


def import_upload(scene: UploadedFile | None, files: list[UploadedFile], directory: Path,
                  main: str | None = None, limits: UploadLimits = UploadLimits()
                  ) -> ImportedUpload:
    """Lay the upload out as a folder inside `directory` (`service.upload_tree`:
    the scene file and the files at their relative paths, or an archive
    unpacked), find its main scene file and import it with every path
    resolved inside that folder only."""
    tree = UploadTree(directory / "tree", limits)
    if scene is not None and (kind := archive_kind(scene.filename, scene.path)):
        if files:
            raise InvalidRequest("files[0]", "send an archive alone (its folder holds the "
                                             "scene's files), or a scene file with its files")
        tree.unpack("scene", scene.filename, scene.path, kind, directory / "archive.tar")
        source = tree.main_file(main)
    elif scene is not None:
        if main is not None:
            raise InvalidRequest("main", "names the scene file inside an archive or among "
                                         "files sent without a scene part; with a scene part, "
                                         "that is the scene file")
        source = tree.add_part("scene", _scene_name(scene), scene.path)
        for upload in files:
            tree.add_part(upload.where, upload.filename, upload.path)
    elif files:
        for upload in files:
            tree.add_part(upload.where, upload.filename, upload.path)
        source = tree.main_file(main)
    else:
        raise InvalidRequest("scene", "field required: the scene file or an archive of its "
                                      "folder (curl -F scene=@room.json, -F scene=@room.zip)")
    doc, assets, report = _import(tree.root, source, tree.name)
    name = scene_name(tree.root / source, tree.root, tree.name)
    return ImportedUpload(doc, assets, report, source, name or "uploaded")


def _scene_name(scene: UploadedFile) -> str:
    """The scene part's path in the upload: its file name, with the suffix its
    content implies when the name has none of a scene file (a JSON scene sent
    as "room" or without a name, as older clients may)."""
    name = scene.filename
    if name and scene_suffix(name):
        return name
    with open(scene.path, "rb") as fh:
        head = fh.read(4096).lstrip(b"\xef\xbb\xbf \t\r\n")
    suffix = (".glb" if head.startswith(b"glTF") else ".xml" if head.startswith(b"<") else
              ".json" if head.startswith((b"{", b"[")) or not head else None)
    if suffix is None:
        raise InvalidRequest("scene", f"{name or 'the scene part'!r} is neither a scene file "
                                      f"({', '.join(SCENE_SUFFIXES)}) nor an archive "
                                      f"({', '.join(ARCHIVE_SUFFIXES)})")
    base = name.rstrip("/").rsplit("/", 1)[-1] if name else ""
    return (base or "scene") + suffix


MAX_REPORT = 500  # entries kept of an import report (then one saying how many more)


def _report(entries) -> list[dict]:
    """An importer's report entries as JSON objects, bounded: a hostile file
    can ask for a hundred thousand ignored elements."""
    out = []
    for entry in entries[:MAX_REPORT]:
        line = getattr(entry, "line", None)
        out.append({"element": str(getattr(entry, "element", ""))[:300],
                    "file": str(getattr(entry, "file", ""))[:1024],
                    "line": line if isinstance(line, int) else None,
                    "action": str(getattr(entry, "action", ""))[:1000]})
    if len(entries) > MAX_REPORT:
        out.append({"element": "", "file": "", "line": None,
                    "action": f"{len(entries) - MAX_REPORT} more entries not kept"})
    return out


def _import(root: Path, source: str, root_name: str
            ) -> tuple[dict, dict[str, bytes], list[dict]]:
    """(resolved document, assets, report) of the scene file `source` of the
    folder `root` (which stands for a folder called `root_name`, "" if not
    known: `scene_name`); SceneError for what is wrong in it."""
    path = root / source
    try:
        if scene_suffix(source) == ".json":
            _parse_scene_file(path, source)  # its messages name line and column
        imported = import_scene(path, root=root, root_name=root_name)
        resolved = resolve_document(imported.doc, assets=imported.assets)
        return resolved, dict(resolved.assets), _report(list(imported.report))
    except SceneError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError, RecursionError,
            OverflowError, UnicodeError) as exc:
        # What the importer or validator did not anticipate is still the client's error.
        raise SceneError(f"malformed scene ({type(exc).__name__}: {exc})") from None


def _triangles(imported: ImportedUpload) -> int:
    return triangle_count(imported.doc)


def _parse_scene_file(path: Path, name: str) -> dict:
    """The scene file's JSON object; errors name the line and column."""
    data = path.read_bytes()
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
