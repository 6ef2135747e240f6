"""A fresh `rayfarm serve` in embedded mode for a benchmark, once it answers /healthz.

    from embedded import embedded_service   # bench/ is a script's sys.path[0]

    with embedded_service(workers=1, env={"RAYFARM_MAX_UPLOAD_BYTES": str(1 << 30)}) as farm:
        with httpx.Client(base_url=farm.base, headers=farm.headers) as client:
            client.post("/jobs", json=...)
        status(farm.pid)                     # the service process, for /proc readings

The service sees this process's environment without any RAYFARM_ setting (so
no broker: the local pool, SQLite in the data dir), then the data dir,
`workers` render processes, a fresh admin token (or `token`) and `env`. It
runs in a process group of its own; leaving the block sends the group
SIGTERM, then SIGKILL after `stop_seconds`, and removes a data dir it made.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator


@dataclass(frozen=True)
class Service:
    proc: subprocess.Popen
    base: str  # http://127.0.0.1:<port>
    port: int
    token: str  # the admin's
    data_dir: Path

    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}


def rayfarm_script() -> str:
    """The `rayfarm` console script of this interpreter's environment."""
    return str(Path(sys.executable).with_name("rayfarm"))


@contextmanager
def embedded_service(*, workers: int = 1, env: dict[str, str] | None = None,
                     data_dir: Path | None = None, command: list[str] | None = None,
                     cwd: Path | None = None, token: str | None = None,
                     loglevel: str | None = None, log: Path | None = None,
                     timeout: float = 900, stop_seconds: float = 60) -> Iterator[Service]:
    """`command` + `serve ...` (default: this environment's `rayfarm`; another
    checkout's with `--rayfarm` or `[python, "-m", "service"]` and `cwd`) on a
    free port of 127.0.0.1, its output to `log` or nowhere. `data_dir` None: a
    temporary one, removed afterwards. `timeout` is generous: the first start
    after a renderer edit compiles the kernels."""
    import httpx

    made = data_dir is None
    data_dir = Path(tempfile.mkdtemp(prefix="rayfarm-bench-")) if made else Path(data_dir)
    token = token or "rf_bench_" + os.urandom(24).hex()
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    child_env = {k: v for k, v in os.environ.items() if not k.startswith("RAYFARM_")}
    child_env.update(RAYFARM_DATA_DIR=str(data_dir), RAYFARM_LOCAL_WORKERS=str(workers),
                     RAYFARM_ADMIN_TOKEN=token, PYTHONUNBUFFERED="1", **(env or {}))
    args = [*(command or [rayfarm_script()]), "serve", "--host", "127.0.0.1", "--port", str(port),
            *(["--loglevel", loglevel] if loglevel else [])]
    output = log.open("wb") if log else subprocess.DEVNULL
    proc = None
    try:
        proc = subprocess.Popen(args, env=child_env, cwd=cwd, stdout=output,
                                stderr=subprocess.STDOUT, start_new_session=True)
        service = Service(proc, f"http://127.0.0.1:{port}", port, token, data_dir)
        deadline = time.monotonic() + timeout
        while True:
            if proc.poll() is not None:
                said = f":\n{log.read_text(errors='replace')}" if log else " (no log kept)"
                raise RuntimeError(f"rayfarm serve exited with {proc.returncode}{said}")
            try:
                if httpx.get(f"{service.base}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"rayfarm serve did not answer /healthz in {timeout:.0f} s")
            time.sleep(0.2)
        yield service
    finally:
        if proc is not None:
            _stop_group(proc, stop_seconds)
        if log:
            output.close()
        if made:
            shutil.rmtree(data_dir, ignore_errors=True)


def _stop_group(proc: subprocess.Popen, seconds: float) -> None:
    """SIGTERM to the service's process group (it and its render processes),
    then SIGKILL to whatever of the group is left (after `seconds` at most)."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(seconds)
    except subprocess.TimeoutExpired:
        pass
    except ProcessLookupError:
        return
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()
