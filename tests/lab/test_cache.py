"""prdp_petsc.lab.training.cache: scene data kept on disk between runs."""

import numpy as np

from prdp_petsc.lab.training.cache import cache_folder, disk_cached


def test_disk_cache_off_computes_every_time(monkeypatch):
    monkeypatch.setenv("PRDP_PETSC_CACHE", "")
    calls = []
    assert cache_folder() is None
    for _ in range(2):
        disk_cached("t", "k", lambda: calls.append(1) or np.ones(2))
    assert len(calls) == 2


def test_disk_cache_keys_on_the_sources(tmp_path, monkeypatch):
    monkeypatch.setenv("PRDP_PETSC_CACHE", str(tmp_path / "cache"))
    source = tmp_path / "scheme.py"
    source.write_text("a = 1")
    first = disk_cached("t", "n4", lambda: np.arange(3.0), sources=[source])
    assert np.array_equal(disk_cached("t", "n4", lambda: np.zeros(3), sources=[source]), first)
    assert len(list((tmp_path / "cache").glob("t_*_n4.npy"))) == 1
    source.write_text("a = 2")  # a changed scheme never reads the old data
    assert not disk_cached("t", "n4", lambda: np.zeros(3), sources=[source]).any()
    assert len(list((tmp_path / "cache").glob("t_*_n4.npy"))) == 2
