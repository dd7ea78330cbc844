"""neuralrt in other processes and threads: a child forked after OpenMP work is refused in one line
(it hung, or numba killed it); spawned children answer as the parent does."""

import subprocess
import sys
import textwrap

import pytest

_SCRIPT = textwrap.dedent("""
    import multiprocessing as mp, sys, torch
    import neuralrt
    from neuralrt import MeshBLAS, Rays, load_mesh

    def work(n):
        try:
            blas = MeshBLAS(load_mesh("procedural:statue:0"))
            o = torch.randn(n, 3, generator=torch.Generator().manual_seed(n)) * 3
            return int(blas.intersect(Rays(o, -o)).hit.sum())
        except neuralrt.NeuralRTError as exc:
            return str(exc)

    if __name__ == "__main__":
        if sys.argv[2] == "neuralrt":
            parent = work(20000)  # OpenMP's threads run here first
        elif sys.argv[2] == "import":  # no parallel region yet (importing torch starts a thread of its own)
            parent = 1
        else:  # torch's alone (the child hung in torch's, then numba's, first parallel region)
            a = torch.randn(1000, 1000)
            parent = int((a @ a).sum() != 0)
            if sys.argv[2] == "torch-then-one-thread":
                torch.set_num_threads(1)  # (its OpenMP threads still exist)
        with mp.get_context(sys.argv[1]).Pool(1) as pool:
            print(parent, pool.apply_async(work, (20000,)).get(timeout=120), flush=True)
""")


@pytest.mark.skipif(sys.platform != "linux", reason="fork with GNU OpenMP: Linux")
@pytest.mark.parametrize("start", ["fork", "spawn"])
@pytest.mark.parametrize("parent_work", ["neuralrt", "torch", "torch-then-one-thread"])
def test_a_child_process_answers_or_says_why_it_cannot(tmp_path, start, parent_work):
    (tmp_path / "pool.py").write_text(_SCRIPT)
    done = subprocess.run([sys.executable, str(tmp_path / "pool.py"), start, parent_work], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    parent, child = done.stdout.strip().split(" ", 1)
    if start == "fork":
        assert child.startswith("MeshBLAS: this process was forked") and "get_context('spawn')" in child
    elif parent_work == "neuralrt":
        assert child == parent
    else:
        assert int(child) > 0


@pytest.mark.skipif(sys.platform != "linux", reason="fork with GNU OpenMP: Linux")
def test_a_fork_after_importing_alone_answers(tmp_path):
    # The first version of the torch check refused it: importing torch starts a thread.
    (tmp_path / "pool.py").write_text(_SCRIPT)
    done = subprocess.run([sys.executable, str(tmp_path / "pool.py"), "fork", "import"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout.split()[1]) > 0


@pytest.mark.skipif(sys.platform != "linux", reason="fork with GNU OpenMP: Linux")
def test_a_fork_after_torch_work_answers_on_a_fork_safe_numba_layer(tmp_path):
    # What the README says: with NUMBA_THREADING_LAYER=workqueue the child answers (its torch on
    # one thread: torch's own first parallel region hung there too).
    import os

    (tmp_path / "pool.py").write_text(_SCRIPT)
    done = subprocess.run([sys.executable, str(tmp_path / "pool.py"), "fork", "torch"], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "NUMBA_THREADING_LAYER": "workqueue"})
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout.split()[1]) > 0


@pytest.mark.skipif(sys.platform != "linux", reason="numba's threading layers as on Linux")
def test_a_training_on_numbas_workqueue_layer_draws_its_batches_in_turn(tmp_path):
    # workqueue aborts the process when two threads run parallel regions at once: a training that
    # drew its next batch on a second thread died with SIGABRT ("Concurrent access has been detected").
    import os

    code = ("import sys\n"
            "from neuralrt import api\n"
            "from neuralrt.fork_guard import numba_regions_thread_safe\n"
            "record = api.train('procedural:statue:0', sys.argv[1], preset='lq', steps=40, batch=1024, progress=False)\n"
            "print(numba_regions_thread_safe(), record['training']['batches_drawn_ahead'])\n")
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path / "m.nrt")], capture_output=True, text=True,
                          timeout=600, env={**os.environ, "NUMBA_THREADING_LAYER": "workqueue"})
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["False", "False"]

