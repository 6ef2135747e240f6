"""The two commands: `.ci/run`, the README's opening and dev.py's install stamp."""

from __future__ import annotations

import importlib.util
import os
import re
import stat
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def dev():
    spec = importlib.util.spec_from_file_location("rayfarm_dev_script", ROOT / "dev.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test01_ci_run_exists_and_calls_dev_test():
    script = ROOT / ".ci" / "run"
    assert script.is_file()
    assert script.stat().st_mode & stat.S_IXUSR, ".ci/run should be executable"
    text = script.read_text()
    assert text.startswith("#!/usr/bin/env bash")
    assert re.search(r"^python3 dev\.py test\b", text, re.M)
    assert "apt-get install -y redis-server" in text


def test02_readme_opens_with_the_two_commands():
    commands = re.findall(r"^\s*(python3 dev\.py \S+)", (ROOT / "README.md").read_text(), re.M)
    assert commands[:2] == ["python3 dev.py farm", "python3 dev.py test"]


def test03_dev_is_stdlib_only():
    text = (ROOT / "dev.py").read_text()
    imported = set(re.findall(r"^(?:import|from) (\w+)", text, re.M))
    assert imported <= {"__future__", "argparse", "hashlib", "os", "subprocess", "sys",
                        "time", "venv", "pathlib"}, imported


def test04_stamp_tracks_pyproject(dev, tmp_path):
    (tmp_path / "pyproject.toml").write_text('[project]\nname = "x"\n')
    venv_dir = tmp_path / ".venv"
    (venv_dir / "bin").mkdir(parents=True)
    (venv_dir / "bin" / "python").write_text("")
    assert not dev.stamp_is_current(venv_dir, tmp_path)  # never installed
    dev.write_stamp(venv_dir, tmp_path)
    assert dev.stamp_is_current(venv_dir, tmp_path)
    assert not dev.stamp_is_current(venv_dir, tmp_path, extras="test,mitsuba")
    (tmp_path / "pyproject.toml").write_text('[project]\nname = "x"\ndependencies = ["numpy"]\n')
    assert not dev.stamp_is_current(venv_dir, tmp_path)  # dependencies changed
    dev.write_stamp(venv_dir, tmp_path)
    (venv_dir / "bin" / "python").unlink()
    assert not dev.stamp_is_current(venv_dir, tmp_path)  # venv broken


def test05_ensure_venv_skips_install_when_stamp_current(dev, tmp_path, monkeypatch):
    (tmp_path / "pyproject.toml").write_text('[project]\nname = "x"\n')
    venv_dir = tmp_path / ".venv"
    (venv_dir / "bin").mkdir(parents=True)
    (venv_dir / "bin" / "python").write_text("")
    calls = []
    monkeypatch.setattr(dev, "run", lambda cmd, **kw: calls.append(cmd))
    dev.ensure_venv(tmp_path)
    assert len(calls) == 1 and calls[0][-2:] == ["-e", ".[test]"]
    dev.ensure_venv(tmp_path)
    assert len(calls) == 1, "second run must reuse the install"
    (tmp_path / "pyproject.toml").write_text('[project]\nname = "y"\n')
    dev.ensure_venv(tmp_path)
    assert len(calls) == 2
    assert os.path.exists(venv_dir / dev.STAMP_NAME)
