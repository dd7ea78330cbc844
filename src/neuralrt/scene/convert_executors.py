"""Who trains a conversion's models: one contract ("train these jobs, yield each result as it
finishes"), two executors.

`convert_scene` decides what to train (one `TrainingJob` per unique mesh whose model is not
already in the models folder), hands the jobs to an executor and writes each `TrainedModel` into
the models folder as it arrives:

- `LocalExecutor` trains them one after another in this process (the behaviour before Ray).
- `RayExecutor` runs one Ray task per job, on a local Ray instance (this machine's cores) or an
  existing cluster (``address``). Each task asks for ``cpus_per_model`` CPUs and
  ``gpus_per_model`` GPUs (one by default when training on CUDA). A mesh is put into Ray's object
  store once by the driver, so workers never read or generate the scene; a task returns the
  model file's bytes and the driver writes the file, so no shared filesystem is needed for the
  models. Tasks checkpoint to the models folder's absolute path: a worker that dies is retried by Ray
  (``max_retries``) and resumes from that checkpoint where the path is visible to it (this
  machine, or a shared filesystem).

Training is bit-reproducible for a fixed number of torch and numba threads (the hash-grid
gradient is summed per thread), so both executors take ``threads`` (threads per model) and set
both libraries to it while a job trains; `LocalExecutor` leaves the process's settings alone by
default, `RayExecutor` uses ``cpus_per_model`` threads by default.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import sys
import tempfile
import threading
import time
import warnings
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from urllib.parse import urlparse

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..arguments import check_count, given
from ..errors import ConfigError, NeuralRTError, validation_message
from ..geometry.mesh import Mesh
from ..io.files import write_atomically
from ..io.run_lock import held_alone
from ..methods import MethodConfig, MethodSpec
from ..progress import progress_bar, redraw_due

__all__ = [
    "TrainingJob", "TrainedModel", "Executor", "LocalExecutor", "RayExecutor", "RayOptions", "EXECUTORS",
    "make_executor", "training_threads",
]

EXECUTORS = ("local", "ray")
INSTALL_HINT = "pip install ray (the cluster extra: pip install -e '.[cluster]' in the neuralrt checkout)"
_PROGRESS_SECONDS = 0.5  # how often workers report and the driver redraws


@dataclass(frozen=True)
class TrainingJob:
    """One model to train: its file stem in the models folder (``name-meshhash-confighash``), the
    mesh, the full config, where it checkpoints, and a description for progress lines."""

    key: str
    mesh: Mesh
    config: MethodConfig
    method: MethodSpec  # shipped to workers so a method registered outside neuralrt is known there too
    checkpoint: Path
    description: str


@dataclass
class TrainedModel:
    """A finished job: the model (local) or its file's bytes (Ray), and where and how it trained."""

    key: str
    seconds: float  # wall time of the job, model construction and ground truth included
    rays_per_second: float
    resumed_from: int | None
    where: str  # "local", or the Ray node's address
    threads: tuple[int, int] | None  # (torch, numba) threads while training
    model: object | None = None
    model_file: bytes | None = None

    def save(self, path: Path) -> None:
        """Write the model file (atomically, like every output)."""
        if self.model is not None:
            self.model.save(path)
        else:
            write_atomically(path, lambda tmp: Path(tmp).write_bytes(self.model_file), fsync=True)


@contextmanager
def training_threads(threads: int | None):
    """Set torch's and numba's thread counts to ``threads`` (None: leave them) and restore them after.
    numba's count is per calling thread and capped by ``NUMBA_NUM_THREADS`` (the core count)."""
    if threads is None:
        yield None
        return
    import numba
    import torch

    from ..host_threads import numba_threads

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with numba_threads(threads):
            yield torch.get_num_threads(), numba.get_num_threads()
    finally:
        torch.set_num_threads(before)


def _current_threads() -> tuple[int, int]:
    import numba
    import torch

    return torch.get_num_threads(), numba.get_num_threads()


def _train_job(job: TrainingJob, mesh: Mesh, device: str, *, threads: int | None, progress: bool, on_step=None):
    """Train one job here (in this process or a Ray worker); returns (model, seconds, threads used)."""
    from ..training.api import train

    start = time.perf_counter()
    _drop_unreadable_checkpoint(job)
    with training_threads(threads) as used:
        model = train(mesh, job.config, progress=progress, device=device, checkpoint=job.checkpoint, resume=True,
                      on_step=on_step)
        used = used or _current_threads()
    return model, time.perf_counter() - start, used


def _drop_unreadable_checkpoint(job: TrainingJob) -> None:
    """A conversion resumes its own checkpoints (named by mesh and config): one that cannot be read
    back (truncated, corrupted) would fail every rerun the same way, so it is removed, said, and
    the model trains from the start."""
    from ..errors import ModelFileError
    from ..io.model_file import read_model_file
    from ..training.trainer import CHECKPOINT_METHOD

    path = Path(job.checkpoint) if job.checkpoint is not None else None
    if path is None or not path.is_file():
        return
    try:
        read_model_file(path, method=CHECKPOINT_METHOD)  # (every array's checksum, as resuming reads them)
    except ModelFileError as exc:
        path.unlink(missing_ok=True)
        warnings.warn(f"{job.key}: its checkpoint cannot be resumed ({exc}): removed, the model trains from the start",
                      stacklevel=2)


class Executor(ABC):
    """Contract: ``with executor: for result in executor.run(jobs): ...`` trains every job and
    yields each `TrainedModel` as it finishes (any order). Entering checks that the executor can
    run (before any long work); leaving stops whatever is still running. ``skip(job)``, where given,
    is asked just before a job starts where the executor starts them one at a time (local): True
    leaves it out, with no result (another process trained that model meanwhile)."""

    name = "executor"

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        pass

    @abstractmethod
    def run(self, jobs: list[TrainingJob], skip: Callable[[TrainingJob], bool] | None = None) -> Iterator[TrainedModel]:
        """Train every job; yield each result as it finishes."""


class LocalExecutor(Executor):
    """Jobs one after another in this process, each with the trainer's own progress bar."""

    name = "local"

    def __init__(self, *, device: str = "cpu", progress: bool = True, threads: int | None = None):
        self.device, self.progress, self.threads = device, progress, threads

    def run(self, jobs: list[TrainingJob], skip: Callable[[TrainingJob], bool] | None = None) -> Iterator[TrainedModel]:
        for k, job in enumerate(jobs):
            if skip is not None and skip(job):
                continue
            if self.progress:
                print(f"[{k + 1}/{len(jobs)}] training {job.description}", file=sys.stderr, flush=True)  # (stdout is the result: --json)
            # (held until the caller has saved the model: a conversion waiting for this one then finds it)
            with held_alone(job.checkpoint) if job.checkpoint is not None else contextlib.nullcontext():
                model, seconds, used = _train_job(job, job.mesh, self.device, threads=self.threads, progress=self.progress)
                record = model.training_record
                yield TrainedModel(job.key, seconds, record.get("rays_per_second", 0.0), record.get("resumed_from"),
                                   "local", used, model=model)


# --- Ray ------------------------------------------------------------------------------------------


MAX_THREADS = 4096  # threads per model, at most (torch's count is a C int: 2**31 was an OverflowError traceback)
_RAY_OPTIONS = ("address", "cpus_per_model", "gpus_per_model", "threads_per_model", "max_retries")


class RayOptions(BaseModel):
    """Settings of the Ray executor (the CLI's flags of the same names)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # (--cpus-per-model inf: one line)

    address: str | None = Field(None, description="existing cluster: 'auto', HOST:PORT or ray://HOST:PORT; "
                                                  "None: start a local Ray instance on this machine's cores")
    cpus_per_model: float = Field(1.0, gt=0, strict=True, description="Ray CPUs each training task asks for")
    gpus_per_model: float | None = Field(None, ge=0, strict=True, description="Ray GPUs each task asks for (default: 1 on cuda, 0 on cpu; "
                                                                 "a fraction shares a GPU)")
    threads_per_model: int | None = Field(None, ge=1, le=MAX_THREADS, strict=True, description="torch and numba threads of each task "
                                                                  "(default: cpus_per_model, at least 1)")
    max_retries: int = Field(3, ge=0, le=1000, strict=True, description="times Ray reruns a task whose worker died (it resumes from its checkpoint)")

    @classmethod
    def parse(cls, **values) -> "RayOptions":
        try:
            return cls(**{k: v for k, v in values.items() if v is not None})
        except ValidationError as exc:
            msg = validation_message(exc)
            for key in _RAY_OPTIONS:
                msg = msg.replace(f"{key}:", f"{given(key)}:")
            raise ConfigError(msg) from None


def _import_ray():
    try:
        import ray
    except ImportError:
        raise ConfigError(f"{given('executor', 'ray')} needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def _no_cluster_hint(named: str) -> str:
    left_out = "unset RAY_ADDRESS" if named.startswith("RAY_ADDRESS=") else f"leave {given('address')} out"
    return f"start one with `ray start --head` on the head node, or {left_out} for a local Ray instance"


def cluster_address(address: str | None) -> str | None:
    """The cluster to use: ``address``, else ``RAY_ADDRESS`` as Ray reads it (set by `ray job
    submit`), else None (a local instance)."""
    return address if address is not None else (os.environ.get("RAY_ADDRESS") or None)


def _named(address: str, given_address: str | None) -> str:
    """The address as the user gave it: ``--address X`` (``address='X'``), or ``RAY_ADDRESS=X``
    where ``given_address`` is None."""
    return given("address", address) if given_address is not None else f"RAY_ADDRESS={address}"


# A client's HTTP/2 connection preface and an empty SETTINGS frame: a gRPC server (Ray's GCS, the
# Ray Client server) answers with its own SETTINGS frame at once; anything else does not.
_HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + b"\x00\x00\x00\x04\x00\x00\x00\x00\x00"
_SETTINGS_FRAME = 0x04


def _python_sigterm_handler():
    """The Python function handling SIGTERM (the CLI's clean stop), or None (none, or not the main
    thread, where no handler can be set)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    handler = signal.getsignal(signal.SIGTERM)
    return handler if callable(handler) else None


def _host_port(address: str, named: str) -> tuple[str, int]:
    """(host, port) of HOST:PORT or ray://HOST:PORT; a one-line error for anything else."""
    parsed = urlparse(address if "://" in address else f"tcp://{address}")
    try:
        host, port = parsed.hostname, parsed.port
    except ValueError:
        host = port = None
    if not host or not port:
        raise ConfigError(f"{named}: expected auto, HOST:PORT or ray://HOST:PORT")
    return host, port


def _probe(address: str, named: str, timeout: float = 3.0) -> None:
    """One-line error unless a gRPC server (as Ray's are) answers at ``address`` (HOST:PORT or
    ray://HOST:PORT): Ray itself retries an unreachable address for minutes, and an address where
    another kind of server listens forever."""
    if address == "auto":
        return  # Ray finds the cluster on this machine, or says at once that there is none
    host, port = _host_port(address, named)
    try:
        with socket.create_connection((host, port), timeout=timeout) as conn:
            conn.settimeout(timeout)
            conn.sendall(_HTTP2_PREFACE)
            head = conn.recv(9)
    except OSError as exc:
        raise ConfigError(f"{named}: no Ray cluster reachable ({exc.strerror or exc}); {_no_cluster_hint(named)}") from None
    if len(head) < 9 or head[3] != _SETTINGS_FRAME:
        raise ConfigError(f"{named}: something listens there, but not Ray (no gRPC answer); give the Ray "
                          f"head's GCS port (`ray start --head --port`, 6379 by default) or ray://HOST:10001")


class _ProgressBoard:
    """A Ray actor (no CPU) that workers report to and the driver reads: key -> latest report."""

    def __init__(self):
        self.rows: dict[str, dict] = {}

    def report(self, key: str, row: dict) -> None:
        old = self.rows.get(key)
        if old is not None and old["pid"] != row["pid"]:
            row["attempt"] = old["attempt"] + 1  # a new worker took the job over (Ray's retry)
        else:
            row["attempt"] = old["attempt"] if old else 1
        self.rows[key] = row

    def snapshot(self) -> dict:
        return self.rows


class _StepReporter:
    """The worker's ``on_step`` hook: step, steps and running rays/s to the board, twice a second."""

    def __init__(self, board, key: str, steps: int, batch_size: int, node: str):
        self.board, self.key, self.steps, self.batch = board, key, steps, batch_size
        self.node, self.pid = node, os.getpid()
        self.first: tuple[int, float] | None = None
        self.last = 0.0

    def __call__(self, step: int, optimizer) -> None:
        now = time.monotonic()
        if self.first is None:
            self.first = (step, now)
        if now - self.last < _PROGRESS_SECONDS and step + 1 < self.steps:
            return
        self.last = now
        rate = (step - self.first[0]) * self.batch / (now - self.first[1]) if now > self.first[1] else 0.0
        self.board.report.remote(self.key, {"step": step + 1, "steps": self.steps, "rays_per_second": rate,
                                            "resumed_from": self.first[0] or None, "node": self.node, "pid": self.pid})


def _train_on_worker(job: TrainingJob, mesh: Mesh, device: str, threads: int, board) -> TrainedModel:
    """The Ray task: train one job, return the model file's bytes."""
    # Unpickling this function imported neuralrt (and its OpenMP wait settings) before torch.
    import ray
    import torch

    from ..methods import method_names, register_method

    if job.method.name not in method_names():
        register_method(job.method)
    if torch.device(device).type == "cuda" and not torch.cuda.is_available():
        raise NeuralRTError(f"{ray.util.get_node_ip_address()}: the task got no usable CUDA device")
    try:  # checkpoints go to the models folder's path where this node can write it (else: none)
        job.checkpoint.parent.mkdir(parents=True, exist_ok=True)
    except OSError:
        job = replace(job, checkpoint=None)
    node = ray.util.get_node_ip_address()
    reporter = _StepReporter(board, job.key, job.config.training.steps, job.config.training.batch_size, node)
    model, seconds, used = _train_job(job, mesh, device, threads=threads, progress=False, on_step=reporter)
    with tempfile.TemporaryDirectory() as folder:
        path = model.save(Path(folder) / f"{job.key}.nrt")
        data = path.read_bytes()
    record = model.training_record
    return TrainedModel(job.key, seconds, record.get("rays_per_second", 0.0), record.get("resumed_from"), node, used,
                        model_file=data)


def _one_line(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None) or exc  # RayTaskError wraps the worker's exception
    text = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {text[-1] if text else ''}".strip(": ")


class RayExecutor(Executor):
    """One Ray task per job on a local Ray instance or a cluster; a tqdm bar of models done / total
    with each running task's step and rays/s."""

    name = "ray"

    def __init__(self, options: RayOptions, *, device: str = "cpu", progress: bool = True):
        import torch

        self.options, self.progress = options, progress
        self.address = cluster_address(options.address)
        self._named = _named(self.address, options.address) if self.address is not None else ""
        self.device = torch.device(device).type  # a task sees its own GPUs as cuda:0...
        gpus = options.gpus_per_model
        if gpus is None:
            gpus = 1.0 if self.device == "cuda" else 0.0
        if self.device == "cuda" and gpus == 0:
            raise ConfigError(f"{given('gpus_per_model', 0)} with {given('device', 'cuda')}: a task training on CUDA needs a GPU (e.g. 1, or 0.5 to share one)")
        if self.device != "cuda" and gpus > 0:
            raise ConfigError(f"{given('gpus_per_model', options.gpus_per_model)} needs {given('device', 'cuda')} (the tasks train on {self.device})")
        self.gpus = gpus
        self.threads = options.threads_per_model or max(1, int(options.cpus_per_model))
        self._ray = None
        self._started = False  # this executor started (and so stops) the Ray instance
        self._running: dict = {}  # ObjectRef -> TrainingJob of each task still running

    # Ray is reached only when there is something to train (a rerun with every model present needs
    # no cluster and never starts one); entry checks what it can without it.
    def __enter__(self):
        self._ray = _import_ray()
        if self.address is not None:
            if self.address != "auto":
                _host_port(self.address, self._named)  # the syntax now; whether Ray answers there, in `run`
        elif self._ray.is_initialized():
            self._check_resources()
        else:  # the local instance to come gets this machine's cores and GPUs
            import torch

            self._check_resources([{"CPU": os.cpu_count() or 1, "GPU": torch.cuda.device_count() if torch.cuda.is_available() else 0}])
        return self

    def _connect(self) -> None:
        import logging

        ray = self._ray
        if self.address is not None:
            _probe(self.address, self._named)
        if not ray.is_initialized():  # else: a caller's own ray.init (tests, notebooks), used as it is
            ours = _python_sigterm_handler()
            level = logging.WARNING if self.progress else logging.ERROR  # (quiet: not Ray's token notice either)
            try:
                if self.address is None:
                    # "local": always a new instance (a bare ray.init() joins a cluster that `ray start`
                    # left on this machine, and hangs if that one is gone).
                    ray.init(address="local", include_dashboard=False, logging_level=level)
                else:
                    ray.init(address=self.address, logging_level=level)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                if self.address is None:
                    raise ConfigError(f"could not start a local Ray instance ({str(exc).splitlines()[0]})") from None
                if self.address == "auto":
                    raise ConfigError(f"{self._named}: no running Ray cluster found on this machine ({str(exc).splitlines()[0]}); "
                                      f"{_no_cluster_hint(self._named)}") from None
                # Ray sends its token only to a cluster it finds itself ("auto"), never to a given address.
                raise ConfigError(f"{self._named}: could not connect to Ray ({str(exc).splitlines()[0]}); "
                                  f"a cluster with token authentication (Ray's default) needs RAY_AUTH_MODE=token and its "
                                  f"token (RAY_AUTH_TOKEN or ~/.ray/auth_token); on a cluster node {given('address', 'auto')} finds both") from None
            finally:
                if ours is not None:  # Ray's core worker takes SIGTERM (a stack dump, then abort): the command's stop again
                    signal.signal(signal.SIGTERM, ours)
            self._started = True
        self._check_resources()

    def _check_resources(self, nodes: list[dict] | None = None) -> None:
        """Tasks that no node can hold would wait forever: a one-line error instead."""
        if nodes is None:
            nodes = [n["Resources"] for n in self._ray.nodes() if n.get("Alive")]
        if not any(r.get("CPU", 0) >= self.options.cpus_per_model and r.get("GPU", 0) >= self.gpus for r in nodes):
            have = "; ".join(f"{r.get('CPU', 0):g} CPU, {r.get('GPU', 0):g} GPU" for r in nodes) or "no node"
            raise ConfigError(f"no Ray node has {self.options.cpus_per_model:g} CPU and {self.gpus:g} GPU for one model "
                              f"(nodes: {have}); lower --cpus-per-model / --gpus-per-model or add nodes")

    def __exit__(self, *exc) -> None:
        ray, running = self._ray, self._running
        if ray is None or not ray.is_initialized():
            return
        if running:  # interrupted or failed: stop the tasks (their checkpoints stay for the next run)
            for ref in list(running):
                ray.cancel(ref)  # KeyboardInterrupt in the task: temporary files are removed on the way out
            ray.wait(list(running), num_returns=len(running), timeout=10)
            running.clear()
        if self._started:
            ray.shutdown()
            self._started = False

    def run(self, jobs: list[TrainingJob], skip: Callable[[TrainingJob], bool] | None = None) -> Iterator[TrainedModel]:
        # (``skip`` is not asked: every task starts at once, as its caller planned them)
        if not jobs:
            return
        self._connect()
        ray = self._ray
        # On the driver's node: if the board's node died with it, the driver would lose its progress
        # (and, before, the whole run); this node lives as long as the driver does.
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        here = NodeAffinitySchedulingStrategy(node_id=ray.get_runtime_context().get_node_id(), soft=False)
        board = ray.remote(num_cpus=0)(_ProgressBoard).options(scheduling_strategy=here).remote()
        # One task per worker process (max_calls=1): a cancelled task's KeyboardInterrupt can land
        # inside a lazy import (torch imports its compiler, ~1.6 s, when training builds the
        # optimizer) and leave that module half-initialized in the process, and a reused worker
        # then failed every later task there ("partially initialized module 'torch._dynamo'", on
        # a Ray instance that outlives the run: a cluster, a notebook, the tests). A fresh
        # process costs a few seconds of imports, against minutes of training.
        task = ray.remote(max_calls=1)(_train_on_worker)
        running = self._running
        for job in jobs:
            mesh_ref = ray.put(job.mesh)  # once per mesh; the task gets it from the object store
            slim = replace(job, mesh=None)  # the mesh travels by reference, not inside the task's arguments
            ref = task.options(num_cpus=self.options.cpus_per_model, num_gpus=self.gpus, max_retries=self.options.max_retries,
                               retry_exceptions=False, name=f"neuralrt-train:{job.key}").remote(
                slim, mesh_ref, self.device, self.threads, board)
            running[ref] = job
        yield from self._collect(ray, board, len(jobs))

    def _collect(self, ray, board, total: int) -> Iterator[TrainedModel]:
        running, failures, seen = self._running, [], {}
        bar = progress_bar(total=total, desc="models", unit="model", disable=not self.progress, dynamic_ncols=True)
        try:
            while running:
                done, _ = ray.wait(list(running), num_returns=1, timeout=_PROGRESS_SECONDS)
                if self.progress and board is not None:
                    try:
                        self._show(bar, ray.get(board.snapshot.remote(), timeout=10), seen)
                    except ray.exceptions.GetTimeoutError:  # a busy machine (not a lost board): the next redraw asks again
                        pass
                    except ray.exceptions.RayError:  # the board is gone: the models still come, without step counts
                        board = None
                        bar.write("(the progress board was lost: step counts stop, training goes on)", file=sys.stderr)
                for ref in done:
                    job = running.pop(ref)
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayError as exc:
                        failures.append(f"{job.key} ({_one_line(exc)})")
                        continue
                    bar.update(1)
                    if self.progress:
                        bar.write(f"trained {job.description} in {result.seconds:.1f} s on {result.where} "
                                  f"({result.rays_per_second:,.0f} rays/s)", file=sys.stderr)
                    yield result
        finally:
            bar.close()
        if failures:
            raise NeuralRTError(f"training failed for {len(failures)} of {total} model(s): {'; '.join(failures)}; the "
                                f"finished models are in the models folder, run the same command again to retry")

    def _show(self, bar, rows: dict, seen: dict) -> None:
        """Running tasks' step and rays/s in the bar; a line when a task resumes or is retried."""
        running_keys = {job.key: job for job in self._running.values()}
        parts, total_rate = [], 0.0
        for key, row in rows.items():
            if key not in running_keys:
                continue
            if seen.get(key) != row["attempt"]:
                if row["attempt"] > 1 or row["resumed_from"]:
                    resumed = f"from step {row['resumed_from']}" if row["resumed_from"] else "from the start"
                    retry = f" (attempt {row['attempt']}: its first worker died)" if row["attempt"] > 1 else ""
                    bar.write(f"{key}: resumed {resumed}{retry} on {row['node']}", file=sys.stderr)
                seen[key] = row["attempt"]
            total_rate += row["rays_per_second"]
            parts.append(f"{running_keys[key].mesh.name} {row['step']}/{row['steps']} {row['rays_per_second'] / 1e3:.0f}k")
        bar.set_postfix_str(f"{total_rate / 1e3:.0f}k rays/s | " + ", ".join(parts) if parts else "starting",
                            refresh=redraw_due(bar))


def make_executor(name: str, *, device: str = "cpu", progress: bool = True, threads_per_model: int | None = None,
                  **ray_options) -> Executor:
    """``"local"`` or ``"ray"`` with its options (`RayOptions`); bad names or options are one-line errors."""
    if name not in EXECUTORS:
        raise ConfigError(f"{given('executor', name)}: choose from {', '.join(EXECUTORS)}")
    if name == "local":
        ray_only = [given(k) for k, v in ray_options.items() if v is not None]
        if ray_only:
            raise ConfigError(f"{', '.join(ray_only)}: only with {given('executor', 'ray')}")
        threads_per_model = check_count(given("threads_per_model"), threads_per_model, maximum=MAX_THREADS)
        return LocalExecutor(device=device, progress=progress, threads=threads_per_model)
    return RayExecutor(RayOptions.parse(threads_per_model=threads_per_model, **ray_options), device=device, progress=progress)
