"""docker-compose.yml and the Dockerfile (Docker itself cannot run here):
every service's command must exist and the farm must be wired as designed."""

from __future__ import annotations

import shlex
import tomllib
from pathlib import Path

import pytest
import yaml

from service.cli import _parser

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def command_of(service: dict) -> list[str]:
    command = service.get("command", [])
    return shlex.split(command) if isinstance(command, str) else list(command)


def test01_services_redis_api_and_a_scalable_worker(compose):
    services = compose["services"]
    assert {"redis", "api", "worker"} <= set(services)
    worker = services["worker"]
    # --scale worker=N needs no fixed name and no host port.
    assert "container_name" not in worker and "ports" not in worker


def test02_every_command_exists(compose):
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    for name, service in compose["services"].items():
        command = command_of(service)
        image = service.get("image", "")
        if image.split(":")[0].endswith("redis"):
            assert not command or command[0] == "redis-server", name
            continue
        assert command, f"{name} has no command"
        assert command[0] in scripts, f"{name}: {command[0]} is not a console script"
        assert scripts[command[0]] == "service.cli:main"
        args = _parser().parse_args(command[1:])  # exits (fails the test) if unknown
        assert args.command in ("serve", "worker"), name


def test03_api_serves_on_all_interfaces_with_the_broker_and_a_volume(compose):
    api = compose["services"]["api"]
    args = _parser().parse_args(command_of(api)[1:])
    assert (args.command, args.host, args.port) == ("serve", "0.0.0.0", 8000)
    env = api["environment"]
    assert env["RAYFARM_BROKER_URL"].startswith("redis://redis:6379/")
    volume = [v for v in api["volumes"] if v.split(":")[1] == env["RAYFARM_DATA_DIR"]]
    assert volume and volume[0].split(":")[0] in compose["volumes"], "data dir on a named volume"


def test04_workers_use_the_same_broker(compose):
    worker = compose["services"]["worker"]
    assert _parser().parse_args(command_of(worker)[1:]).command == "worker"
    assert worker["environment"]["RAYFARM_BROKER_URL"] == \
        compose["services"]["api"]["environment"]["RAYFARM_BROKER_URL"]


def test05_dockerfile_installs_the_project_and_its_console_script():
    text = (ROOT / "Dockerfile").read_text()
    assert text.startswith("# ") and "FROM python:3.11" in text
    assert "pip install ." in text
    for package in ("renderer", "worker", "service"):
        assert f"COPY {package} " in text
    images = {s.get("image") for s in yaml.safe_load(
        (ROOT / "docker-compose.yml").read_text())["services"].values() if "build" in s}
    assert images == {"rayfarm:latest"}
