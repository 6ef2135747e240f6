"""How soon an event stream ends after its caller's login does.

    python bench/stream_revocation.py            # 5 rounds of each case

An in-process service (TestClient, a temporary data dir, one render process);
an artist's `GET /events` stream, idle or busy (an event of the artist's jobs
every 20 ms), then the login ends: its token revoked over HTTP (DELETE
/tokens), or the user disabled on the ledger itself (as `rayfarm users set
--disable` or another replica would). It prints the seconds from the start of
that call to the end of the stream: min, median and max over the rounds.
The keep-alive interval is set out of reach (an hour), so only the
revocation path (service.revocations) can end the stream.

Figures are in docs/hardening.md.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import threading
import time

ADMIN = "rf_bench-revocation-" + "x" * 24


def main(rounds: int = 5) -> int:
    os.environ["RAYFARM_ADMIN_TOKEN"] = ADMIN
    os.environ["RAYFARM_ALLOWED_HOSTS"] = "testserver"
    from fastapi.testclient import TestClient

    from service import auth
    from service.api.routes import events
    from service.main import create_app
    from service.models import utcnow
    from service.settings import Settings

    events.KEEPALIVE = 3600.0
    scratch = tempfile.TemporaryDirectory(prefix="rayfarm-revocation-")
    app = create_app(Settings(data_dir=scratch.name, local_workers=1))
    results: dict[str, list[float]] = {}
    calls: list[float] = []  # seconds the revoking call itself took
    with TestClient(app, headers={"Authorization": f"Bearer {ADMIN}"}) as admin:
        farm = app.state.farm
        for case in ("idle, token revoked", "busy, token revoked", "idle, user disabled",
                     "busy, user disabled"):
            for n in range(rounds):
                name = f"u{len(results)}x{n}"
                with farm.sessions.begin() as session:
                    auth.add_user(session, name, "artist", utcnow())
                    token, secret = auth.create_token(session, name, utcnow())
                client = TestClient(app, headers={"Authorization": f"Bearer {secret}"})
                stop = threading.Event()
                if case.startswith("busy"):
                    def chatter(owner=name):
                        while not stop.wait(0.02):
                            farm.events.publish("job", "0123456789ab", {"id": "0123456789ab"},
                                                owner=owner)
                    threading.Thread(target=chatter, daemon=True).start()
                with client.stream("GET", "/events") as response:
                    ended: list[float] = []

                    def read():  # a client that keeps up with its stream
                        for _ in response.iter_lines():
                            pass
                        ended.append(time.monotonic())
                    reader = threading.Thread(target=read, daemon=True)
                    reader.start()
                    time.sleep(1.0)  # the stream is open and the watch has read the ledger
                    started = time.monotonic()
                    if case.endswith("revoked"):
                        admin.delete(f"/tokens/{token.id}").raise_for_status()
                    else:
                        with farm.sessions.begin() as session:
                            auth.set_user(session, name, disabled=True)
                    calls.append(time.monotonic() - started)
                    reader.join(60)
                    results.setdefault(case, []).append(ended[0] - started)
                stop.set()
    print(f"seconds from the start of the revoking call to the end of the stream; the call "
          f"itself took {statistics.median(calls):.2f} s (median)")
    print(f"{'case':<22} {'min s':>6} {'median s':>9} {'max s':>6}   ({rounds} rounds)")
    for case, seconds in results.items():
        print(f"{case:<22} {min(seconds):>6.2f} {statistics.median(seconds):>9.2f} "
              f"{max(seconds):>6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]) if len(sys.argv) > 1 else 5))
