"""What a huge request body costs the service: peak RSS, time to the answer,
and /healthz meanwhile.

    python bench/front_door.py                      # 2 GiB bodies to this checkout
    python bench/front_door.py --size 100MiB        # smaller (for code that reads them all)

It starts `rayfarm serve` (embedded: SQLite, one render process, a temporary
data dir) on a free port and sends, to each of several routes, a body of
`--size` bytes twice: declared (Content-Length, only the headers are sent
until the server answers) and chunked (no Content-Length: 64 KiB chunks until
the server answers or closes), once without a token and once with the
admin's. For each it reports the answer's status, the seconds until it came,
the bytes the client got to send (a declared body is sent only if no answer
came within 2 s; what a refused chunked body got to send is mostly the
kernel's socket buffers), the service's RSS before the request and its peak
above that (Linux: /proc/PID/status VmHWM, reset through clear_refs before
each request; memory a former request left allocated is not counted again),
and the slowest /healthz answer while the request was on (polled every 50 ms
from another thread).

To measure the code before the front door was bounded, export that commit's
service and worker (the renderer is the same, so its compiled kernels are
reused) and put them first on the path; keep the size small, since that code
reads every body whole:

    git archive 77e9ea8 service worker | tar -x -C /tmp/base-svc
    PYTHONPATH=/tmp/base-svc python bench/front_door.py --size 100MiB

Figures are in docs/hardening.md.
"""

from __future__ import annotations

import argparse
import re
import select
import shutil
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))
from embedded import embedded_service  # noqa: E402

ROUTES = [("POST", "/auth/login"), ("POST", "/experiments"), ("POST", "/users"),
          ("PATCH", "/jobs/0123456789ab"), ("POST", "/jobs"), ("POST", "/scenes")]
TOKEN = "rf_bench-front-door-" + "x" * 24
CHUNK = b" " * (64 << 10)
# An upload's body starts as one: a scene file part, whose bytes follow.
PART = b'--b\r\nContent-Disposition: form-data; name="scene"; filename="room.json"\r\n\r\n'


def _size(text: str) -> int:
    match = re.fullmatch(r"(\d+)\s*([KMG]i?B)?", text.strip())
    if not match:
        raise argparse.ArgumentTypeError(f"a size like 2GiB or 100MiB, not {text!r}")
    scale = {None: 1, "KiB": 1 << 10, "MiB": 1 << 20, "GiB": 1 << 30,
             "KB": 1 << 10, "MB": 1 << 20, "GB": 1 << 30}[match.group(2)]
    return int(match.group(1)) * scale


def _status(pid: int) -> dict[str, int]:
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in ("VmRSS", "VmHWM"):
            fields[name] = int(value.split()[0]) * 1024
    return fields


def _reset_peak(pid: int) -> bool:
    try:
        Path(f"/proc/{pid}/clear_refs").write_text("5")  # Linux: VmHWM := VmRSS
        return True
    except OSError:
        return False


class HealthPoll:
    """/healthz every 50 ms from a thread; the slowest answer while on."""

    def __init__(self, base: str):
        self.base, self.slowest, self.failed = base, 0.0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    def _run(self):
        with httpx.Client(base_url=self.base, timeout=60) as client:
            while not self._stop.wait(0.05):
                start = time.monotonic()
                try:
                    client.get("/healthz").raise_for_status()
                except httpx.HTTPError:
                    self.failed += 1
                self.slowest = max(self.slowest, time.monotonic() - start)


def _answer(sock: socket.socket, timeout: float = 600) -> bytes:
    sock.settimeout(timeout)
    answer = b""
    while b"\r\n\r\n" not in answer:
        data = sock.recv(4096)
        if not data:
            break
        answer += data
    return answer


def send(host: str, port: int, method: str, path: str, size: int, chunked: bool,
         token: str | None) -> tuple[str, float, int]:
    """(status, seconds to the answer, bytes of the body sent)."""
    kind = "multipart/form-data; boundary=b" if path == "/scenes" else "application/json"
    head = (f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: {kind}\r\n"
            + (f"Authorization: Bearer {token}\r\n" if token else ""))
    first = PART if path == "/scenes" else b"["
    sent = 0
    start = time.monotonic()
    with socket.create_connection((host, port)) as sock:
        if not chunked:
            sock.sendall(f"{head}Content-Length: {size}\r\n\r\n".encode())
            if select.select([sock], [], [], 2)[0]:  # an answer before the body?
                answer = _answer(sock)
            else:  # the server waits for the body: send it
                try:
                    sock.sendall(first)
                    sent = len(first)
                    while sent < size:
                        piece = CHUNK[: size - sent]
                        sock.sendall(piece)
                        sent += len(piece)
                except OSError:
                    pass
                answer = _answer(sock)
        else:
            sock.sendall(f"{head}Transfer-Encoding: chunked\r\n\r\n".encode()
                         + f"{len(first):x}\r\n".encode() + first + b"\r\n")
            frame = f"{len(CHUNK):x}\r\n".encode() + CHUNK + b"\r\n"
            try:
                while sent < size:
                    if select.select([sock], [], [], 0)[0]:
                        break
                    sock.sendall(frame)
                    sent += len(CHUNK)
                else:
                    sock.sendall(b"0\r\n\r\n")
            except OSError:
                pass
            answer = _answer(sock)
    status = answer.split(b" ", 2)[1].decode() if answer else "closed"
    return status, time.monotonic() - start, sent


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=_size, default=2 << 30, help="body size (default 2GiB)")
    args = parser.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="rayfarm-front-door-"))
    try:
        with embedded_service(workers=1, data_dir=workdir / "data", token=TOKEN,
                              loglevel="warning", log=workdir / "serve.log", timeout=300,
                              stop_seconds=20) as server:
            base, port = server.base, server.port
            can_reset = _reset_peak(server.pid)
            print(f"body: {args.size} bytes; service pid {server.pid}; RSS "
                  f"{_status(server.pid)['VmRSS'] / 2**20:.0f} MiB"
                  + ("" if can_reset else " (peak not resettable: deltas are since start)"))
            print(f"{'route':<26} {'token':<6} {'body':<9} {'status':>6} {'seconds':>8} "
                  f"{'sent MiB':>9} {'RSS MiB':>8} {'peak +MiB':>9} {'healthz max s':>13}")
            for method, path in ROUTES:
                for token in (None, TOKEN):
                    for chunked in (False, True):
                        _reset_peak(server.pid)
                        before = _status(server.pid)["VmRSS"]
                        with HealthPoll(base) as health:
                            status, seconds, sent = send("127.0.0.1", port, method, path, args.size,
                                                         chunked, token)
                            time.sleep(0.1)  # what the service does right after the answer
                        peak = _status(server.pid)["VmHWM"] - before
                        print(f"{method + ' ' + path:<26} {'admin' if token else 'none':<6} "
                              f"{'chunked' if chunked else 'declared':<9} {status:>6} "
                              f"{seconds:>8.3f} {sent / 2**20:>9.1f} {before / 2**20:>8.0f} "
                              f"{peak / 2**20:>9.1f} "
                              f"{health.slowest:>13.3f}"
                              + (f"  ({health.failed} /healthz failed)" if health.failed else ""))
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
