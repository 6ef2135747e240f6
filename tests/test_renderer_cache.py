"""The renderer's on-disk cache (renderer/cache.py): a size cap with least
recently used eviction, atomic entries, and a location its user hands it,
never the home directory."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from renderer import cache as C


def _age(cache: C.DiskCache, key: str, seconds_ago: float) -> None:
    """Make an entry look last used `seconds_ago` (deterministic ordering)."""
    when = time.time() - seconds_ago
    os.utime(cache.path(key), (when, when))


def test01_put_beyond_the_cap_evicts_the_least_recently_used(tmp_path):
    cache = C.DiskCache(tmp_path / "c", max_bytes=1000)
    for i in range(4):  # 4 x 300 bytes: the fourth put must evict
        assert cache.put(f"k{i}", bytes([i]) * 300)
        _age(cache, f"k{i}", 100 - i)  # k0 the oldest, k3 the newest
    info = cache.info()
    assert info.bytes <= 1000 and info.entries == 3
    assert cache.get("k0") is None, "the least recently used entry must go first"
    assert [cache.get(f"k{i}") for i in (1, 2, 3)] == [bytes([i]) * 300 for i in (1, 2, 3)]
    for i in range(4, 10):
        cache.put(f"k{i}", bytes([i]) * 300)
        assert cache.info().bytes <= 1000
    assert cache.get("k9") == bytes([9]) * 300  # the entry just put is kept
    assert not [p for p in (tmp_path / "c").iterdir() if not p.name.endswith(".entry")]


def test02_a_read_makes_an_entry_recently_used(tmp_path):
    cache = C.DiskCache(tmp_path / "c", max_bytes=1000)
    for i in range(3):
        cache.put(f"k{i}", b"x" * 300)
        _age(cache, f"k{i}", 100 - i)
    assert cache.get("k0") == b"x" * 300  # k0 was the oldest; now the newest
    cache.put("k3", b"y" * 300)
    assert cache.get("k0") == b"x" * 300
    assert cache.get("k1") is None, "k1 is now the least recently used"
    assert cache.info().bytes <= 1000


def test03_too_big_an_entry_is_not_stored_and_clear_empties(tmp_path):
    cache = C.DiskCache(tmp_path / "c", max_bytes=100)
    assert cache.put("a", b"1" * 50) and not cache.put("big", b"2" * 101)
    assert cache.get("big") is None and cache.get("a") == b"1" * 50
    with pytest.raises(ValueError):
        cache.path("../escape")
    assert cache.clear() == 1 and cache.info().entries == 0 and cache.get("a") is None


def test04_two_processes_share_a_directory(tmp_path):
    """Concurrent puts of two processes: nobody crashes, the cap holds at the end."""
    code = ("import sys; from renderer.cache import DiskCache\n"
            "c = DiskCache(sys.argv[1], 5000)\n"
            "for i in range(200):\n"
            "    c.put(f'{sys.argv[2]}{i % 40}', bytes(400))\n"
            "    c.get(f'a{i % 40}'); c.get(f'b{i % 40}')\n")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "c"), tag])
             for tag in "ab"]
    assert [p.wait(120) for p in procs] == [0, 0]
    cache = C.DiskCache(tmp_path / "c", 5000)
    cache.evict()  # the last put of each process evicted; the total fits
    assert cache.info().bytes <= 5000 and cache.info().entries > 0


def test05_the_location_comes_from_who_runs_the_renderer(tmp_path, monkeypatch):
    monkeypatch.delenv("RAYFARM_CACHE_DIR", raising=False)
    monkeypatch.delenv("RAYFARM_DATA_DIR", raising=False)
    try:
        C.reset()
        assert C.disk_cache("radiosity") is None  # no home directory, no working directory
        monkeypatch.setenv("RAYFARM_DATA_DIR", str(tmp_path / "data"))
        assert C.disk_cache("radiosity").directory == tmp_path / "data" / "cache" / "radiosity"
        monkeypatch.setenv("RAYFARM_CACHE_DIR", str(tmp_path / "env"))
        assert C.disk_cache("radiosity").directory == tmp_path / "env" / "radiosity"
        C.configure(tmp_path / "given", 12345)
        cache = C.disk_cache("radiosity")
        assert cache.directory == tmp_path / "given" / "radiosity" and cache.max_bytes == 12345
    finally:
        C.reset()


def test06_a_radiosity_render_writes_under_the_data_dir_never_home(tmp_path):
    """`renderer.render` (its process pool too) with HOME elsewhere: the solution
    lands in $RAYFARM_DATA_DIR/cache/radiosity and nothing in HOME."""
    home, data = tmp_path / "home", tmp_path / "data"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAYFARM_")}
    env.update(HOME=str(home), RAYFARM_DATA_DIR=str(data), XDG_CACHE_HOME=str(home / ".cache"))
    code = ("from renderer import render, RenderSpec\n"
            "render('cornell-box', RenderSpec(method='radiosity', spp=1, depth=2, width=8,"
            " height=8, tile_size=8, seed=5, options={'patch_size': 0.5, 'ff_rays': 16}),"
            " workers=1)\n")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    entries = list((data / "cache" / "radiosity").glob("*.entry"))
    assert len(entries) >= 2, entries  # the warm-up's solution and this render's
    written = [p for p in Path(home).rglob("*")]
    assert written == [], f"written under HOME: {written}"
