"""The memory the up-front checks count on is the tightest of the kernel's MemAvailable, a memory
cgroup's headroom (a container's or batch job's limit) and an address-space limit (``ulimit -v``):
under such limits a huge render or training batch ended in an allocator traceback, FLIP in a crash."""

import os
import subprocess
import sys

import pytest

import neuralrt.devices
from neuralrt.devices import _cgroup_headroom, available_bytes
from neuralrt.errors import ConfigError

GIB = 1 << 30


def _cgroup(tmp_path, hierarchy: str, levels: dict) -> str:
    """A fake /proc/self/cgroup and cgroup tree; ``levels``: path -> (limit, usage, inactive file)."""
    proc = tmp_path / "cgroup"
    version2 = hierarchy == "v2"
    leaf = max(levels, key=len)
    proc.write_text(f"0::{leaf}\n" if version2 else f"9:pids:/\n4:memory:{leaf}\n1:cpu:/\n")
    base = tmp_path / "fs" / ("" if version2 else "memory")
    for path, (limit, usage, cache) in levels.items():
        folder = base / path.lstrip("/")
        folder.mkdir(parents=True, exist_ok=True)
        names = ("memory.max", "memory.current", "inactive_file") if version2 else \
            ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")
        (folder / names[0]).write_text(f"{limit}\n")
        (folder / names[1]).write_text(f"{usage}\n")
        (folder / "memory.stat").write_text(f"anon 5\n{names[2]} {cache}\nfile 9\n")
    return str(proc)


@pytest.mark.parametrize("hierarchy, unlimited", [("v2", "max"), ("v1", 9223372036854771712)])
def test_a_cgroup_limit_counts_its_tightest_level_with_inactive_cache_as_free(tmp_path, hierarchy, unlimited):
    proc = _cgroup(tmp_path, hierarchy, {"/": (unlimited, 50 * GIB, 0),
                                          "/job": (8 * GIB, 5 * GIB, 1 * GIB),       # 4 GiB left
                                          "/job/step": (unlimited, 3 * GIB, 0)})
    assert _cgroup_headroom(proc, str(tmp_path / "fs")) == 4 * GIB
    unbound = tmp_path / "unbound"
    unbound.mkdir()
    assert _cgroup_headroom(_cgroup(unbound, hierarchy, {"/": (unlimited, 1, 0)}), str(unbound / "fs")) is None
    assert _cgroup_headroom(str(tmp_path / "missing"), str(tmp_path / "fs")) is None


def test_the_checks_take_the_tightest_limit(monkeypatch):
    monkeypatch.setattr(neuralrt.devices, "_mem_available", lambda: 20 * GIB)
    monkeypatch.setattr(neuralrt.devices, "_cgroup_headroom", lambda: 6 * GIB)
    monkeypatch.setattr(neuralrt.devices, "_address_space_headroom", lambda: None)
    assert available_bytes("cpu") == 6 * GIB
    monkeypatch.setattr(neuralrt.devices, "_address_space_headroom", lambda: 2 * GIB)
    assert available_bytes("cpu") == 2 * GIB


@pytest.mark.skipif(sys.platform != "linux", reason="/proc and RLIMIT_AS: Linux")
def test_an_address_space_limit_is_counted():
    # (in a child: the limit binds the whole process)
    code = ("import resource; from neuralrt.devices import _address_space_headroom as h; "
            "hard = resource.getrlimit(resource.RLIMIT_AS)[1]; "  # (a runner may set one already)
            "resource.setrlimit(resource.RLIMIT_AS, (6 << 30 if hard == resource.RLIM_INFINITY else min(6 << 30, hard), hard)); "
            "print(h())")
    left = int(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
    assert 0 < left < 6 << 30


def test_a_training_batch_beyond_the_memory_left_is_refused_before_the_work(monkeypatch, tmp_path):
    from neuralrt import api
    from neuralrt.training.api import TRAINING_BYTES_PER_RAY

    monkeypatch.setattr(neuralrt.devices, "available_bytes", lambda device: 4096 * TRAINING_BYTES_PER_RAY - 1)
    with pytest.raises(ConfigError, match=r"^a training batch of 4,096 rays needs 8,388,608 bytes of memory, 8,388,607 bytes is "
                                          r"available on cpu: give a smaller batch \(training.batch_size\)$"):
        api.train("procedural:statue:0", tmp_path / "m.nrt", batch=4096, steps=1, progress=False)
    assert os.listdir(tmp_path) == []
