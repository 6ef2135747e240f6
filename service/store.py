"""The data directory: scenes by hash, unit films, finished images.

    <data_dir>/data_dir.id                     the data dir's random id (`data_dir_identity`)
    <data_dir>/store/scenes/<hash>.json        canonical scene text
    <data_dir>/store/scenes/<hash>.png         its thumbnail
    <data_dir>/store/assets/<digest>           a mesh or texture blob (renderer.assets)
    <data_dir>/uploads/<random>/               an upload while it is checked (then deleted)
    <data_dir>/jobs/<job_id>/units/<i>.film    a unit's PartialFilm bytes
    <data_dir>/jobs/<job_id>/logs/<i>/<n>.json  unit i's log from its n-th task (JSON)
    <data_dir>/jobs/<job_id>/result.exr        the merged image
    <data_dir>/jobs/<job_id>/preview.png       its tonemapped preview
    <data_dir>/jobs/<job_id>/noise.png         its noise heatmap
    <data_dir>/jobs/<job_id>/preview.watched   empty: its mtime is the last GET of
    <data_dir>/jobs/<job_id>/noise.watched       preview.png / noise.png (service.previews)

Every write is atomic (temporary file + rename), so a reader sees a whole
file or none. Paths are built only from validated ids, so nothing is ever
written outside the data directory.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["Store", "data_dir_identity"]

_HASH = re.compile(r"[0-9a-f]{64}")
_JOB_ID = re.compile(r"[0-9a-f]{6,32}")


def _check(pattern: re.Pattern, value: str, what: str) -> str:
    if not isinstance(value, str) or not pattern.fullmatch(value):
        raise ValueError(f"not a valid {what}: {value!r}")
    return value


def data_dir_identity(root: Path) -> str:
    """The data dir's own random id, made on first use: one directory has one
    id under every path and on every host that mounts it, so the services on
    one ledger can tell whether they share it (`service.leader`)."""
    root = Path(root)
    path = root / "data_dir.id"
    try:
        return path.read_text().strip()
    except FileNotFoundError:
        pass
    root.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=root, prefix=".data_dir.id.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(secrets.token_hex(16) + "\n")
        try:  # a link never replaces the id another service made meanwhile
            os.link(tmp, path)
        except FileExistsError:
            pass
    finally:
        os.unlink(tmp)
    return path.read_text().strip()


class Store:
    """Files of the farm under one root directory."""

    def __init__(self, root: Path):
        self.root = Path(root).resolve()
        (self.root / "store" / "scenes").mkdir(parents=True, exist_ok=True)
        (self.root / "store" / "assets").mkdir(parents=True, exist_ok=True)
        (self.root / "jobs").mkdir(parents=True, exist_ok=True)
        self._remove_stale_uploads()

    # -- paths ---------------------------------------------------------------
    def scene_path(self, scene_hash: str) -> Path:
        return self.root / "store" / "scenes" / f"{_check(_HASH, scene_hash, 'scene hash')}.json"

    @property
    def asset_dir(self) -> Path:
        """Where assets live, one `<digest>` file each (a render process reads them)."""
        return self.root / "store" / "assets"

    def asset_path(self, digest: str) -> Path:
        return self.asset_dir / _check(_HASH, digest, "asset digest")

    def thumbnail_path(self, scene_hash: str) -> Path:
        return self.scene_path(scene_hash).with_suffix(".png")

    def job_dir(self, job_id: str) -> Path:
        return self.root / "jobs" / _check(_JOB_ID, job_id, "job id")

    def unit_path(self, job_id: str, index: int) -> Path:
        return self.job_dir(job_id) / "units" / f"{int(index)}.film"

    def unit_log_dir(self, job_id: str, index: int) -> Path:
        return self.job_dir(job_id) / "logs" / str(int(index))

    def result_path(self, job_id: str) -> Path:
        return self.job_dir(job_id) / "result.exr"

    def preview_path(self, job_id: str) -> Path:
        return self.job_dir(job_id) / "preview.png"

    def noise_path(self, job_id: str) -> Path:
        return self.job_dir(job_id) / "noise.png"

    def denoised_path(self, job_id: str) -> Path:
        return self.job_dir(job_id) / "denoised.png"

    def experiment_dir(self, experiment_id: str) -> Path:
        """An estimator-lab experiment's figures (service.experiments)."""
        return self.root / "experiments" / _check(_JOB_ID, experiment_id, "experiment id")

    def frame_path(self, job_id: str) -> Path:
        """A running job's merged frame as float32 channels (an uncompressed
        .npz, written beside its preview: service.previews), for the HDR viewer."""
        return self.job_dir(job_id) / "frame.npz"

    def partial_paths(self, job_id: str, units: int) -> tuple[Path, Path]:
        """The EXR and PNG of a canceled or failed job's `units` finished units
        (service.results.partial_result): named by their count, so a job retried
        and stopped again gets new ones."""
        d = self.job_dir(job_id)
        return d / f"partial-{int(units)}.exr", d / f"partial-{int(units)}.png"

    def clear_partials(self, job_id: str, keep: int | None = None) -> None:
        """Remove a job's partial results (but those of `keep` units)."""
        for path in self.job_dir(job_id).glob("partial-*.*"):
            if keep is None or path.stem != f"partial-{int(keep)}":
                path.unlink(missing_ok=True)

    def watch_path(self, job_id: str, image: str) -> Path:
        """The marker whose mtime says when `image` ("preview" or "noise") was last fetched."""
        if image not in ("preview", "noise"):
            raise ValueError(f"not a running image: {image!r}")
        return self.job_dir(job_id) / f"{image}.watched"

    # -- who looks at a running job -------------------------------------------
    def mark_watched(self, job_id: str, image: str) -> None:
        """Note that a client fetched the job's `image` ("preview" or "noise")
        now. A file in the data dir, so every replica's GETs reach the
        scheduler's replica. Never creates the job's directory: before its
        first unit there is nothing to watch (the first preview is written
        anyway), and a job deleted meanwhile stays gone."""
        path = self.watch_path(job_id, image)
        try:
            os.utime(path)
        except FileNotFoundError:
            try:
                os.close(os.open(path, os.O_WRONLY | os.O_CREAT, 0o644))
            except FileNotFoundError:
                pass

    def watched_at(self, job_id: str, image: str) -> float:
        """time.time() of the last `mark_watched(job_id, image)`; -inf if never."""
        try:
            return self.watch_path(job_id, image).stat().st_mtime
        except OSError:
            return float("-inf")

    # -- reads and atomic writes ----------------------------------------------
    def put_scene(self, scene_hash: str, text: str) -> None:
        path = self.scene_path(scene_hash)
        if not path.exists():  # content-addressed: an existing file is the same text
            self._write_atomic(path, text.encode())

    def scene_text(self, scene_hash: str) -> str:
        return self.scene_path(scene_hash).read_text()

    def put_asset(self, digest: str, blob: bytes) -> None:
        """Keep an asset under its digest (checked: the name is the content's)."""
        path = self.asset_path(digest)
        if hashlib.sha256(blob).hexdigest() != digest:
            raise ValueError(f"asset bytes do not match the digest {digest[:12]}")
        if not path.exists():  # content-addressed: an existing file is the same bytes
            self._write_atomic(path, blob)

    def put_assets(self, assets: dict[str, bytes]) -> None:
        for digest, blob in assets.items():
            self.put_asset(digest, blob)

    def asset_bytes(self, digest: str) -> bytes:
        """An asset's blob; FileNotFoundError if the store has none (an asset source)."""
        return self.asset_path(digest).read_bytes()

    def has_asset(self, digest: str) -> bool:
        return self.asset_path(digest).is_file()

    def asset_size(self, digest: str) -> int:
        return self.asset_path(digest).stat().st_size

    def put_thumbnail(self, scene_hash: str, png: bytes) -> None:
        self._write_atomic(self.thumbnail_path(scene_hash), png)

    @contextmanager
    def upload_dir(self) -> Iterator[Path]:
        """A new private directory (mode 0700) for one upload, deleted on exit."""
        parent = self.root / "uploads"
        parent.mkdir(exist_ok=True)
        path = Path(tempfile.mkdtemp(dir=parent, prefix="upload-"))
        try:
            yield path
        finally:
            shutil.rmtree(path, ignore_errors=True)

    def _remove_stale_uploads(self, age: float = 24 * 3600) -> None:
        # Left behind only if a service died mid-upload; a day is far past any upload.
        for path in (self.root / "uploads").glob("upload-*"):
            try:
                if time.time() - path.stat().st_mtime > age:
                    shutil.rmtree(path, ignore_errors=True)
            except OSError:
                pass

    def put_unit_film(self, job_id: str, index: int, film: bytes) -> None:
        self._write_atomic(self.unit_path(job_id, index), film)

    def unit_film(self, job_id: str, index: int) -> bytes:
        return self.unit_path(job_id, index).read_bytes()

    def put_unit_log(self, job_id: str, index: int, task: int, entry: dict) -> None:
        """Keep what unit `index`'s `task`-th task logged (one file per task, so
        a retry never overwrites the attempt before it)."""
        # not fsynced: a log is a diagnostic, and one lost to a power cut loses
        # no render (readers skip a missing or cut-short file); the film is.
        self._write_atomic(self.unit_log_dir(job_id, index) / f"{int(task)}.json",
                           json.dumps(entry).encode(), durable=False)

    def unit_logs(self, job_id: str, index: int) -> list[dict]:
        """Unit `index`'s kept logs, oldest task first (none: an empty list)."""
        directory = self.unit_log_dir(job_id, index)
        found = []
        for path in directory.glob("*.json") if directory.is_dir() else ():
            if path.stem.isascii() and path.stem.isdigit():
                try:
                    found.append((int(path.stem), json.loads(path.read_text())))
                except (OSError, ValueError):  # removed meanwhile (requeued), or cut short
                    continue
        return [entry for _, entry in sorted(found, key=lambda pair: pair[0])]

    def clear_results(self, job_id: str) -> None:
        """Forget a job's unit films, logs and images (it is requeued)."""
        shutil.rmtree(self.job_dir(job_id) / "units", ignore_errors=True)
        shutil.rmtree(self.job_dir(job_id) / "logs", ignore_errors=True)
        self.result_path(job_id).unlink(missing_ok=True)
        self.preview_path(job_id).unlink(missing_ok=True)
        self.noise_path(job_id).unlink(missing_ok=True)
        self.denoised_path(job_id).unlink(missing_ok=True)
        self.frame_path(job_id).unlink(missing_ok=True)
        self.clear_partials(job_id)

    def delete_job(self, job_id: str) -> None:
        """Remove every file of a job (it is deleted)."""
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    @staticmethod
    def _write_atomic(path: Path, data: bytes, durable: bool = True) -> None:
        """Readers see the old file or all of `data`, never part of it; `durable`:
        on disk before this returns (fsync), not only in the page cache."""
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                if durable:
                    fh.flush()
                    os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
