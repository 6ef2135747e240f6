"""/scenes: the built-in scenes and uploaded ones: upload, list, inspect,
thumbnail, delete."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status
from fastapi.responses import FileResponse
from starlette.concurrency import run_in_threadpool

from ... import admission, scenes
from ...errors import InvalidRequest
from ...models import utcnow
from ...schemas import ScenePublic
from ...upload_tree import UploadLimits
from ..auth import ActorDep
from ..deps import FarmDep, SessionDep
from ..errors import responses
from ..multipart import receive_parts

router = APIRouter(prefix="/scenes", tags=["scenes"])

MAX_MAIN = 1024  # bytes of the main field: a path in the upload

_UPLOAD_BODY = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object", "properties": {
        "scene": {"type": "string", "format": "binary",
                  "description": "the scene file (.json: docs/scene-format.md, Mitsuba .xml, "
                                 ".gltf, .glb), its file name its path in the scene's folder; "
                                 "or one archive of the folder (.zip, .tar, .tar.gz)"},
        "files": {"type": "array", "items": {"type": "string", "format": "binary"},
                  "description": "the files the scene names (meshes, textures, included "
                                 "files), each file name its path relative to the folder "
                                 "(models/Mesh000.obj); without a scene part: a whole folder"},
        "main": {"type": "string", "maxLength": MAX_MAIN,
                 "description": "the scene file's path in an archive or folder holding "
                                "several at its top level"},
    }}}}}}


def _public(farm, info: scenes.SceneInfo) -> ScenePublic:
    return ScenePublic.from_info(info, farm.store.thumbnail_path(info.scene_hash).is_file())


@router.post("", status_code=status.HTTP_201_CREATED, response_model=ScenePublic,
             openapi_extra=_UPLOAD_BODY,
             responses={200: {"model": ScenePublic, "description": "uploaded before: the same id"},
                        **responses(403, 409, 413, 422, 429, 507)})
async def upload_scene(request: Request, farm: FarmDep, actor: ActorDep,
                       response: Response) -> ScenePublic:
    """Upload a scene: a scene file (multipart field `scene`) with the files
    it names (field `files`, repeated, each named by its relative path), or
    one archive of its folder (field `scene`: .zip, .tar, .tar.gz), or a
    folder's files alone (`files`); `main` picks the scene file where the
    folder's top level holds several. Hostile paths and archives are refused
    (422 or 413 naming the file or member). It is imported (Mitsuba XML,
    glTF or rayfarm JSON) in a child process (422 naming the field, or the
    place in the scene: file and line), stored by content hash with its
    assets and its import report, and its thumbnail rendered in the
    background. 201 with a Location; 200 with the existing record for
    content uploaded before; 429 with Retry-After while
    RAYFARM_MAX_CONCURRENT_UPLOADS uploads are under way; 507 with
    Retry-After while the disk is full (the upload is not read)."""
    settings = farm.settings
    farm.disk.check_room()
    admission.check_upload_rate(farm.limiter, settings, actor)  # 429 past uploads per hour
    with farm.uploads.hold(), farm.store.upload_dir() as directory:  # 429 if too many at once
        parts = await receive_parts(
            request, directory, fields={"scene": 1, "files": settings.max_upload_files,
                                        "main": 1},
            too_many={"files": f"at most {settings.max_upload_files} files per upload "
                               "(RAYFARM_MAX_UPLOAD_FILES)"})
        scene_parts = [p for p in parts if p.field == "scene"]
        scene = (scenes.UploadedFile("scene", 0, scene_parts[0].filename or "",
                                     scene_parts[0].path) if scene_parts else None)
        files = [scenes.UploadedFile("files", i, p.filename or "", p.path)
                 for i, p in enumerate(p for p in parts if p.field == "files")]
        main = next((_main_field(p) for p in parts if p.field == "main"), None)
        if scene is None and not files:
            raise InvalidRequest("scene", "field required: the scene file or an archive of its "
                                          "folder (curl -F scene=@room.json, -F scene=@room.zip)")
        info, created = await run_in_threadpool(
            scenes.add_upload, farm.sessions, farm.store, actor, scene, files, directory,
            utcnow(), main, UploadLimits.from_settings(settings))
    farm.thumbnails.request(info.scene_hash)  # a no-op if it exists
    if created:
        response.headers["Location"] = f"/scenes/{info.id}"
    else:
        response.status_code = status.HTTP_200_OK
    return _public(farm, info)


def _main_field(part) -> str:
    """The text of the `main` form field: a path in the upload."""
    if part.size > MAX_MAIN:
        raise InvalidRequest("main", f"longer than {MAX_MAIN} bytes (a path in the upload)")
    try:
        return part.path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise InvalidRequest("main", "not UTF-8 text (a path in the upload)") from None


@router.get("", response_model=list[ScenePublic])
def list_scenes(session: SessionDep, farm: FarmDep, actor: ActorDep) -> list[ScenePublic]:
    """Built-in scenes (id = name), then the caller's uploads (id = hash; admins
    and viewers: every upload), newest first; a job's `scene` names either by
    its id (or is an inline scene document)."""
    return [_public(farm, info) for info in scenes.list_scenes(session, actor)]


@router.get("/{scene_id}", response_model=ScenePublic, responses=responses(404))
def get_scene(scene_id: str, session: SessionDep, farm: FarmDep, actor: ActorDep) -> ScenePublic:
    """One scene (404 naming the id)."""
    return _public(farm, scenes.get_scene(session, actor, scene_id))


@router.get("/{scene_id}/thumbnail.png", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}, **responses(404)})
def thumbnail(scene_id: str, session: SessionDep, farm: FarmDep, actor: ActorDep) -> FileResponse:
    """The scene's thumbnail, at most 128 px on the long side (404 until rendered)."""
    return FileResponse(scenes.thumbnail_file(session, farm.store, actor, scene_id),
                        media_type="image/png")


@router.delete("/{scene_id}", status_code=status.HTTP_204_NO_CONTENT,
               responses=responses(403, 404, 409))
def delete_scene(scene_id: str, session: SessionDep, actor: ActorDep) -> Response:
    """Remove the caller's claim on an uploaded scene (409 for a built-in one);
    others who uploaded the same content keep it. Jobs submitted with it keep
    running: they carry its hash, and its text stays in the store."""
    scenes.delete_scene(session, actor, scene_id)
    session.commit()
    return Response(status_code=status.HTTP_204_NO_CONTENT)
