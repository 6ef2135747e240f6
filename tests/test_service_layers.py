"""The three layers import in one direction: service -> worker -> renderer."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"renderer": {"worker", "service"}, "worker": {"service"}}


def imported_packages(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test01_lower_layers_never_import_higher_ones(layer):
    offenders = {str(p.relative_to(ROOT)): sorted(imported_packages(p) & FORBIDDEN[layer])
                 for p in (ROOT / layer).rglob("*.py")}
    assert {k: v for k, v in offenders.items() if v} == {}


def test02_domain_code_never_imports_fastapi():
    # Only service/api (and main.py, which assembles the app) know HTTP.
    offenders = [str(p.relative_to(ROOT)) for p in (ROOT / "service").rglob("*.py")
                 if "api" not in p.relative_to(ROOT / "service").parts
                 and p.name != "main.py" and imported_packages(p) & {"fastapi", "starlette"}]
    assert offenders == []


def test03_workers_never_touch_the_ledger():
    offenders = [str(p.relative_to(ROOT)) for p in (ROOT / "worker").rglob("*.py")
                 if "sqlalchemy" in imported_packages(p)]
    assert offenders == []


def test04_the_client_speaks_http_only():
    # service/client.py ships alone: the standard library and httpx, nothing of the
    # service or the renderer; the client commands add tqdm and the client itself.
    import sys

    allowed = set(sys.stdlib_module_names) | {"__future__"}
    for name, extra, siblings in (("client.py", {"httpx"}, set()),
                                  ("client_cli.py", {"tqdm"}, {"client"})):
        path = ROOT / "service" / name
        assert imported_packages(path) - allowed - extra == set(), name
        tree = ast.parse(path.read_text(), filename=str(path))
        relative = {node.module for node in ast.walk(tree)
                    if isinstance(node, ast.ImportFrom) and node.level > 0}
        assert relative <= siblings, (name, relative)
