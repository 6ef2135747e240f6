#!/usr/bin/env python3
"""The two commands: run the farm, run the tests. Standard library only.

    python3 dev.py farm [--host HOST] [--port PORT]        # rayfarm serve, embedded mode
    python3 dev.py test [pytest args...]                  # python -m pytest

Both first make sure `.venv` exists with `pip install -e '.[test]'` done for
the current pyproject.toml: the install is skipped when the stamp file
`.venv/.rayfarm-install-stamp` holds the hash of pyproject.toml (and of the
extras installed), so a second run starts at once and an edit to the
dependencies reinstalls them.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import time
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
EXTRAS = "test"
STAMP_NAME = ".rayfarm-install-stamp"


def say(message: str) -> None:
    print(f"dev.py: {message}", flush=True)


def venv_python(venv_dir: Path) -> Path:
    return venv_dir / "bin" / "python"


def install_fingerprint(root: Path, extras: str = EXTRAS) -> str:
    """What the stamp records: a hash of pyproject.toml, the extras and the
    interpreter version (a new Python needs a new install too)."""
    digest = hashlib.sha256()
    digest.update((root / "pyproject.toml").read_bytes())
    digest.update(f"\n[{extras}]\n{sys.version_info[0]}.{sys.version_info[1]}".encode())
    return digest.hexdigest()


def stamp_is_current(venv_dir: Path, root: Path, extras: str = EXTRAS) -> bool:
    stamp = venv_dir / STAMP_NAME
    return (venv_python(venv_dir).exists() and stamp.exists()
            and stamp.read_text().strip() == install_fingerprint(root, extras))


def write_stamp(venv_dir: Path, root: Path, extras: str = EXTRAS) -> None:
    (venv_dir / STAMP_NAME).write_text(install_fingerprint(root, extras) + "\n")


def run(cmd: list[str], **kwargs) -> None:
    say("$ " + " ".join(str(c) for c in cmd))
    subprocess.run([str(c) for c in cmd], check=True, **kwargs)


def ensure_venv(root: Path = ROOT, extras: str = EXTRAS) -> Path:
    """Create or reuse `<root>/.venv`, installing the project only when the
    stamp is missing or stale. Returns the venv directory."""
    venv_dir = root / ".venv"
    t0 = time.monotonic()
    if not venv_python(venv_dir).exists():
        say(f"creating virtualenv {venv_dir}")
        try:
            venv.create(venv_dir, with_pip=True, clear=venv_dir.exists())
        except Exception as exc:  # ensurepip missing is the usual Debian/Ubuntu case
            raise SystemExit(f"dev.py: could not create {venv_dir}: {exc}\n"
                             "dev.py: on Debian/Ubuntu install python3-venv "
                             "(apt-get install python3-venv) and retry")
    if stamp_is_current(venv_dir, root, extras):
        say(f"reusing {venv_dir} (pyproject.toml unchanged since the last install)")
        return venv_dir
    say(f"installing rayfarm into {venv_dir} (pyproject.toml changed or first run)")
    run([venv_python(venv_dir), "-m", "pip", "install", "--disable-pip-version-check",
         "-e", f".[{extras}]"], cwd=root)
    write_stamp(venv_dir, root, extras)
    say(f"install done in {time.monotonic() - t0:.1f} s")
    return venv_dir


def exec_in_root(argv: list[str]) -> None:
    """Replace this process with `argv`, run from the repository root."""
    say("$ " + " ".join(argv))
    os.chdir(ROOT)
    sys.stdout.flush()
    os.execv(argv[0], argv)


def cmd_farm(args: argparse.Namespace, _rest: list[str]) -> None:
    venv_dir = ensure_venv()
    mode = ("Celery on " + os.environ["RAYFARM_BROKER_URL"] if os.environ.get("RAYFARM_BROKER_URL")
            else "embedded: SQLite ledger, local process pool, no Redis")
    serve = [str(venv_dir / "bin" / "rayfarm"), "serve"]
    for flag, value in (("--host", args.host), ("--port", args.port)):
        if value is not None:  # otherwise `rayfarm serve`'s own default (127.0.0.1:8000)
            serve += [flag, str(value)]
    say(f"starting the service ({mode})")
    exec_in_root(serve)


def cmd_test(args: argparse.Namespace, rest: list[str]) -> None:
    venv_dir = ensure_venv()
    exec_in_root([str(venv_python(venv_dir)), "-m", "pytest", *rest])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="dev.py", description="Set up .venv and run the rayfarm service or its tests.")
    sub = parser.add_subparsers(dest="command", required=True)
    farm = sub.add_parser("farm", help="run `rayfarm serve` (embedded mode by default)")
    farm.add_argument("--host", help="interface to listen on (rayfarm serve's default if omitted)")
    farm.add_argument("--port", type=int, help="TCP port (rayfarm serve's default if omitted)")
    farm.set_defaults(func=cmd_farm)
    sub.add_parser("test", help="run pytest; every later argument goes to pytest verbatim")
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["test"]:  # pass pytest's arguments through untouched
        cmd_test(argparse.Namespace(), argv[1:])
        return
    args = parser.parse_args(argv)
    args.func(args, [])


if __name__ == "__main__":
    main()
