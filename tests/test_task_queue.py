"""`neuralrt.task_queue`: every task taken exactly once, by whichever worker is free."""

import numba
import numpy as np
import pytest

from neuralrt.task_queue import take_task, task_count, task_workers


@numba.njit(parallel=True)
def _run_tasks(n_tasks, n_workers, runs, worker_of, cost):
    next_task = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):
        while True:
            task = take_task(next_task)
            if task >= n_tasks:
                break
            runs[task] += 1
            worker_of[task] = worker
            x = 0.0
            for i in range(cost[task]):  # work that varies with the task
                x += np.sqrt(i + x)
            if x < 0:
                runs[task] = -1


@pytest.mark.parametrize("n_tasks", [0, 1, 5, 257])
def test_each_task_runs_once(n_tasks):
    cost = np.random.default_rng(0).integers(0, 20_000, n_tasks)
    runs, worker_of = np.zeros(n_tasks, np.int64), np.full(n_tasks, -1, np.int64)
    workers = task_workers(n_tasks)
    _run_tasks(n_tasks, workers, runs, worker_of, cost)
    assert (runs == 1).all()
    assert ((worker_of >= 0) & (worker_of < workers)).all()


def test_workers_one_per_thread_at_most_one_per_task():
    assert task_workers(0) == 1
    assert task_workers(1) == 1
    assert task_workers(10_000) == numba.get_num_threads()


def test_task_count_holds_min_items_a_task_and_caps_per_thread():
    threads = numba.get_num_threads()
    assert task_count(0) == 1 and task_count(0, 64) == 1  # at least one task
    assert task_count(5) == 5  # one item a task by default
    assert task_count(130, 64) == 3  # ceil(130 / 64)
    assert task_count(10**9) == 8 * threads
    assert task_count(10**9, 256, 32) == 32 * threads


def test_counter_values_increase():
    @numba.njit
    def take_three(counter):
        return take_task(counter), take_task(counter), take_task(counter)

    counter = np.array([7], np.int64)
    assert take_three(counter) == (7, 8, 9)
    assert counter[0] == 10


def test_rejects_other_counters():
    @numba.njit
    def take(counter):
        return take_task(counter)

    with pytest.raises(numba.core.errors.TypingError):
        take(np.zeros(1, np.int32))
