"""The `rayfarm` command.

    rayfarm serve --host 0.0.0.0 --port 8000     the HTTP service (+ scheduler)
    rayfarm worker --concurrency 4                a Celery worker (needs RAYFARM_BROKER_URL)
    rayfarm render ...                            render locally (the renderer's own CLI)
    rayfarm users add|set|list, tokens create|revoke|list   accounts, on the ledger
    rayfarm cache info|clear                      the renderer's on-disk caches (radiosity)

    rayfarm submit SCENE --spp 64 ...             the client commands (service/client_cli.py):
    rayfarm watch|fetch|cancel ID                 they talk to a service over HTTP (--server URL
    rayfarm jobs | workers | logs JOB [UNIT]      or RAYFARM_SERVER)

Configuration comes from the environment (`RAYFARM_*`, see worker/settings.py).
"""

from __future__ import annotations

import argparse
import logging.config
import os
import sys

from .admin_cli import add_admin_commands
from .client_cli import add_client_commands

__all__ = ["main"]


class _RedactTokens:
    """A logging filter for uvicorn's access log: the login URL's token never
    reaches a log file (`/?token=rf_...` is logged as `/?token=...`)."""

    def filter(self, record) -> bool:
        import re

        if isinstance(record.args, tuple) and len(record.args) >= 3:
            args = list(record.args)
            args[2] = re.sub(r"(token=)[^&\s]+", r"\1...", str(args[2]))
            record.args = tuple(args)
        return True


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    from .api.security import allowed_hosts
    from .auth import admin_token_path, bootstrap_admin
    from .db import open_ledger
    from .leader import DataDirConflict, open_leadership
    from .main import create_app
    from .settings import Settings

    settings = Settings()
    settings.keep_files_private()  # before the ledger, the store or a log file is made
    if not settings.allowed_hosts:  # the names of the address it listens on
        settings.allowed_hosts = allowed_hosts([], bind=args.host)
    engine, sessions = open_ledger(settings)
    try:
        try:  # checked again, with this service recorded, as it starts
            open_leadership(settings, engine).check(settings.data_dir)
        except DataDirConflict as exc:
            print(f"rayfarm serve: {exc}", file=sys.stderr)
            return 2
        secret = bootstrap_admin(sessions, settings.data_dir, settings.admin_token)
    finally:
        engine.dispose()
    host = "127.0.0.1" if args.host in ("0.0.0.0", "::", "") else args.host
    if ":" in host:
        host = f"[{host}]"
    if secret:  # as Jupyter does: one URL that logs the browser in
        print(f"\n    rayfarm is starting; open the dashboard (this URL logs you in as admin):"
              f"\n\n        http://{host}:{args.port}/?token={secret}\n\n"
              f"    The CLI on this machine reads the same token from "
              f"{admin_token_path(settings.data_dir).resolve()}.\n", flush=True)
    else:
        print(f"\n    rayfarm is starting. No admin login token on file "
              f"({admin_token_path(settings.data_dir)}); make one with "
              "`rayfarm tokens create admin`\n", flush=True)
    import logging

    log_config = uvicorn.config.LOGGING_CONFIG
    if settings.log_format == "json":
        log_config = json_log_config(args.loglevel)
        logging.config.dictConfig(log_config)  # the app's own loggers, from here on
    logging.getLogger("uvicorn.access").addFilter(_RedactTokens())
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level=args.loglevel,
                log_config=log_config)
    return 0


def json_log_config(level: str = "info") -> dict:
    """A logging config (dictConfig) for `rayfarm serve` with RAYFARM_LOG_FORMAT=json:
    uvicorn's loggers and every other one write JSON lines to stderr."""
    handler = {"class": "logging.StreamHandler", "formatter": "json",
               "stream": "ext://sys.stderr"}
    return {
        "version": 1, "disable_existing_loggers": False,
        "formatters": {"json": {"()": "renderer.unitlog.JsonLogFormatter"}},
        "handlers": {"stderr": handler},
        "loggers": {name: {"handlers": ["stderr"], "level": level.upper(), "propagate": False}
                    for name in ("uvicorn", "uvicorn.access")},
        "root": {"handlers": ["stderr"], "level": level.upper()},
    }


def _worker(args: argparse.Namespace) -> int:
    from worker.celery_app import create_celery_app
    from worker.keys import QUEUE
    from worker.settings import Settings

    settings = Settings()
    if not settings.broker_url:
        print("rayfarm worker: set RAYFARM_BROKER_URL (e.g. redis://localhost:6379/0)",
              file=sys.stderr)
        return 2
    settings.keep_files_private()  # its caches, logs and the render processes' files
    app = create_celery_app(settings)
    # One single-threaded render process per core (prefork); by default a
    # unique node name so several workers on one host don't collide. A name
    # given with --name stays across restarts, and with it what the farm knows
    # of the worker (drained, blocklisted).
    name = args.name or f"rayfarm-{os.getpid()}@%h"
    if "@" not in name:
        name += "@%h"
    app.worker_main([
        "worker", "--pool=prefork", f"--concurrency={args.concurrency}",
        f"--loglevel={args.loglevel.upper()}", f"--queues={QUEUE}",
        f"--hostname={name}", "--without-gossip", "--without-mingle",
    ])
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rayfarm", description="rayfarm: a render farm")
    sub = parser.add_subparsers(dest="command", required=True)
    serve = sub.add_parser("serve", help="run the HTTP service and its scheduler")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument("--loglevel", default="info",
                       choices=["critical", "error", "warning", "info", "debug"])
    serve.set_defaults(run=_serve)
    worker = sub.add_parser("worker", help="run a Celery worker (RAYFARM_BROKER_URL)")
    worker.add_argument("--concurrency", type=int, default=os.cpu_count() or 1,
                        help="render processes (default: one per core)")
    worker.add_argument("--loglevel", default="info",
                        choices=["critical", "error", "warning", "info", "debug"])
    worker.add_argument("--name", default=None,
                        help="the worker's name, kept across restarts (NAME or NAME@HOST; "
                             "default: rayfarm-<pid>@<host>, new at every start)")
    worker.set_defaults(run=_worker)
    sub.add_parser("render", help="render a scene locally (see `rayfarm render --help`)",
                   add_help=False)
    add_client_commands(sub)
    add_admin_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "render":
        # The renderer owns its CLI; forward everything after "render".
        from renderer.cli import main as render_main

        return render_main(argv[1:]) or 0
    args = _parser().parse_args(argv)
    return args.run(args)
