"""docker-compose.yml, deploy/ (Prometheus) and the Dockerfile (Docker itself
cannot run containers here): the compose file parses with `docker compose
config` (or Debian's `docker-compose`, which .ci/run installs when neither is
there), every service's command exists, and the farm is wired as designed:
two api replicas on one PostgreSQL ledger, scalable workers, Redis, and a
Prometheus scraping both replicas with alerts that name real metrics."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
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


API_REPLICAS = ("api-1", "api-2")


def test01_services_postgres_redis_two_apis_workers_and_prometheus(compose):
    services = compose["services"]
    assert {"postgres", "redis", *API_REPLICAS, "worker", "prometheus"} <= set(services)
    worker = services["worker"]
    # --scale worker=N needs no fixed name and no host port.
    assert "container_name" not in worker and "ports" not in worker
    assert int(worker["deploy"]["replicas"]) >= 2


def test02_every_command_exists(compose):
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    for name, service in compose["services"].items():
        command = command_of(service)
        image = service.get("image", "")
        if image.split(":")[0].endswith("redis"):
            assert not command or command[0] == "redis-server", name
            continue
        if "build" not in service and not image.startswith("rayfarm"):
            continue  # postgres, prometheus: their images' own commands
        assert command, f"{name} has no command"
        assert command[0] in scripts, f"{name}: {command[0]} is not a console script"
        assert scripts[command[0]] == "service.cli:main"
        args = _parser().parse_args(command[1:])  # exits (fails the test) if unknown
        assert args.command in ("serve", "worker"), name


def test03_each_api_serves_on_all_interfaces_with_the_broker_and_a_volume(compose):
    for name in API_REPLICAS:
        api = compose["services"][name]
        args = _parser().parse_args(command_of(api)[1:])
        assert (args.command, args.host, args.port) == ("serve", "0.0.0.0", 8000), name
        env = api["environment"]
        assert env["RAYFARM_BROKER_URL"].startswith("redis://redis:6379/")
        volume = [v for v in api["volumes"] if v.split(":")[1] == env["RAYFARM_DATA_DIR"]]
        assert volume and volume[0].split(":")[0] in compose["volumes"], \
            "data dir on a named volume"


def test03b_the_api_replicas_share_one_postgres_ledger_and_one_data_volume(compose):
    services = compose["services"]
    apis = [services[name] for name in API_REPLICAS]
    urls = {api["environment"]["RAYFARM_DATABASE_URL"] for api in apis}
    assert len(urls) == 1, urls
    [url] = urls
    assert url.startswith("postgresql://") and "@postgres:5432/" in url
    from service.settings import Settings
    assert Settings(database_url=url).sqlalchemy_url.startswith("postgresql+psycopg://")
    assert len({tuple(api["volumes"]) for api in apis}) == 1  # one store for both
    host_ports = [p.split(":")[0] for api in apis for p in api["ports"]]
    assert len(set(host_ports)) == len(apis), host_ports  # both reachable at once
    for api in apis:  # they start once the ledger and the broker answer
        assert api["depends_on"]["postgres"]["condition"] == "service_healthy"
        assert api["depends_on"]["redis"]["condition"] == "service_healthy"
    postgres = services["postgres"]
    assert postgres["image"].startswith("postgres:") and "healthcheck" in postgres
    assert postgres["environment"]["POSTGRES_DB"] == url.rsplit("/", 1)[1]


def test04_workers_use_the_same_broker(compose):
    worker = compose["services"]["worker"]
    assert _parser().parse_args(command_of(worker)[1:]).command == "worker"
    for name in API_REPLICAS:
        assert worker["environment"]["RAYFARM_BROKER_URL"] == \
            compose["services"][name]["environment"]["RAYFARM_BROKER_URL"]


def test05_dockerfile_installs_the_project_and_its_console_script():
    text = (ROOT / "Dockerfile").read_text()
    assert text.startswith("# ") and "FROM python:3.11" in text
    assert "pip install ." in text
    for package in ("renderer", "worker", "service"):
        assert f"COPY {package} " in text
    images = {s.get("image") for s in yaml.safe_load(
        (ROOT / "docker-compose.yml").read_text())["services"].values() if "build" in s}
    assert images == {"rayfarm:latest"}



def _compose_command() -> list[str] | None:
    """`docker compose` (the plugin) or Debian's `docker-compose`, whichever runs."""
    candidates = [["docker", "compose"]] if shutil.which("docker") else []
    if shutil.which("docker-compose"):
        candidates.append(["docker-compose"])
    for command in candidates:
        probe = subprocess.run([*command, "version"], capture_output=True, text=True, timeout=60)
        if probe.returncode == 0:
            return command
    return None


def test06_docker_compose_config_parses_the_file():
    command = _compose_command()
    if command is None:
        if os.environ.get("CI"):
            pytest.fail("neither `docker compose` nor `docker-compose` runs (.ci/run installs "
                        "Debian's docker-compose)")
        pytest.skip("neither `docker compose` nor `docker-compose` is installed")
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAYFARM_")}
    out = subprocess.run([*command, "-f", str(ROOT / "docker-compose.yml"), "config"],
                         capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    assert out.returncode == 0, out.stderr
    resolved = yaml.safe_load(out.stdout)
    assert {"postgres", "redis", *API_REPLICAS, "worker", "prometheus"} <= \
        set(resolved["services"])
    # The anchor's environment reached both replicas, defaults filled in.
    for name in API_REPLICAS:
        env = resolved["services"][name]["environment"]
        assert env["RAYFARM_DATABASE_URL"].startswith("postgresql://rayfarm:rayfarm@postgres")


def _metric_families() -> set[str]:
    from service.metrics import _GAUGES, PrometheusMetrics

    return {family.name for family in PrometheusMetrics().registry.collect()} | set(_GAUGES)


def test07_prometheus_scrapes_both_replicas_and_its_alerts_name_real_metrics(compose):
    prometheus = compose["services"]["prometheus"]
    mounts = {v.split(":")[0]: v.split(":")[1] for v in prometheus["volumes"]}
    config_path = ROOT / "deploy" / "prometheus.yml"
    assert mounts["./deploy/prometheus.yml"] == "/etc/prometheus/prometheus.yml"
    config = yaml.safe_load(config_path.read_text())
    [job] = [j for j in config["scrape_configs"] if j["job_name"] == "rayfarm-api"]
    assert job.get("metrics_path", "/metrics") == "/metrics"
    targets = {t for group in job["static_configs"] for t in group["targets"]}
    assert targets == {f"{name}:8000" for name in API_REPLICAS}
    for rule_file in config["rule_files"]:  # mounted from deploy/
        [local] = [src for src, dst in mounts.items() if dst == rule_file]
        assert (ROOT / local).is_file(), local
    families = _metric_families()
    rules = yaml.safe_load((ROOT / "deploy" / "alerts.yml").read_text())
    named = set()
    for group in rules["groups"]:
        for rule in group["rules"]:
            assert rule["alert"] and rule["expr"] and rule["annotations"]["summary"]
            named |= set(re.findall(r"rayfarm_[a-z_]+", str(rule["expr"])))
    suffixes = ("_total", "_bucket", "_count", "_sum")
    for name in named:
        base = next((name[: -len(s)] for s in suffixes if name.endswith(s)), name)
        assert base in families, f"alerts.yml names {name}, which /metrics does not have"


def test08_the_operations_page_lists_every_metric_and_is_linked():
    page = (ROOT / "docs" / "operations.md").read_text()
    for family in _metric_families():
        assert f"`{family}" in page, f"docs/operations.md does not explain {family}"
    for topic in ("## Metrics", "## Alerts", "## Draining a worker", "## Failover",
                  "rayfarm workers disable", "/workers/{name}/disable", "rayfarm logs"):
        assert topic in page, topic
    assert "docs/operations.md" in (ROOT / "README.md").read_text()
