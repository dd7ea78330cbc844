"""The shared training loop: the per-step hook, method statistics in the record's extra dict."""

import os
import threading
import time

import pytest
import torch

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.geometry.procedural import sphere
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel
from neuralrt.training import prefetch
from neuralrt.training.ray_distribution import BoxRayDistribution
from neuralrt.training.trainer import train_model


def test_hook_runs_after_every_step_and_extra_holds_method_statistics():
    mesh = sphere(2)
    model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq"))
    rays = BoxRayDistribution(MeshBLAS(mesh), model.box, pool_size=1024, seed=0)
    calls = []

    def hook(step, optimizer):
        assert isinstance(optimizer, torch.optim.Adam)
        calls.append(step)

    record = train_model(model, rays, steps=4, batch_size=256, learning_rate=0.01, progress=False, on_step=hook)
    assert calls == [0, 1, 2, 3]
    assert record.steps == 4 and record.rays == 4 * 256
    assert set(record.extra) == {"truncated_fraction"} and 0.0 <= record.extra["truncated_fraction"] <= 1.0


def test_rays_per_second_leaves_out_the_first_step_which_loads_the_kernels():
    mesh = sphere(2)
    model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq"))
    rays = BoxRayDistribution(MeshBLAS(mesh), model.box, pool_size=1024, seed=0)

    def first_step_compiles(step, optimizer):
        if step == 0:
            time.sleep(0.5)  # (as a cold numba cache's compile would)

    record = train_model(model, rays, steps=4, batch_size=256, learning_rate=0.01, progress=False, on_step=first_step_compiles)
    assert record.first_step_seconds >= 0.5 and record.first_step_rays == 256 and record.seconds > record.first_step_seconds
    assert record.rays_per_second == pytest.approx(3 * 256 / (record.seconds - record.first_step_seconds))
    assert record.rays_per_second > 4 * 256 / 0.5  # (all four steps over the whole time would be below this)


def test_training_runs_on_every_device(device):
    from neuralrt.training.api import train

    mesh = sphere(2)
    model = train(mesh, LSNIFConfig.preset("lq").with_training(steps=5, batch_size=512), progress=False, device=device)
    assert model.device.type == device.type and model.training_record["device"] == device.type
    assert model.training_record["steps"] == 5 and model.training_record["compute_precision"] in ("bf16", "fp32")


def _short_run(mesh, steps, on_model=None, **kw):
    model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq"))
    if on_model is not None:
        on_model(model)
    rays = BoxRayDistribution(MeshBLAS(mesh), model.box, pool_size=1024, seed=0)
    train_model(model, rays, steps=steps, batch_size=256, learning_rate=0.01, progress=False, **kw)
    return model.state_dict()


def test_adam_l2_is_added_to_every_gradient():
    # N-BVH's authors train with Adam's l2 = 1e-8 (tiny-cuda-nn's l2_reg: l2 x parameter added to the
    # gradient): table entries no ray touched move only with it.
    mesh = sphere(2)
    start = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq")).encoder.table.detach().clone()
    seen = []
    plain = _short_run(mesh, 2, on_step=lambda step, opt: seen.append(opt.param_groups[0]["weight_decay"]))
    with_l2 = _short_run(mesh, 2, adam_l2=0.5)
    untouched = plain["encoder.table"] == start
    assert seen == [0.0, 0.0] and untouched.float().mean() > 0.5
    assert not (with_l2["encoder.table"][untouched] == start[untouched]).any()


def test_nbvh_trains_with_the_authors_adam():
    from neuralrt.methods.nbvh_config import NBVHConfig

    tc = NBVHConfig.preset("cpu").training
    assert (tc.adam_betas, tc.adam_eps, tc.adam_l2) == ((0.9, 0.999), 1e-8, 1e-8) and LSNIFConfig().training.adam_l2 == 0.0


def test_a_key_added_at_its_old_behaviour_keeps_caches_and_checkpoints():
    # training.adam_l2 came after models were cached and checkpoints written: at 0 (how LSNIF always
    # trained) it is left out of the form they are matched by, so neither retrains nor is orphaned.
    from neuralrt.methods.nbvh_config import NBVHConfig

    assert "adam_l2" not in LSNIFConfig.preset("hq").model_defining()["training"]
    assert LSNIFConfig.preset("hq").with_training(adam_l2=1e-3).model_defining()["training"]["adam_l2"] == 1e-3
    assert NBVHConfig.preset("cpu").model_defining()["training"]["adam_l2"] == 1e-8  # trains differently now


def _assert_same_parameters(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_overlapped_sampling_trains_the_same_model():
    """Drawing batch k+1 on the background thread while step k runs gives the same batches, in order."""
    mesh = sphere(2)
    serial = _short_run(mesh, 5, overlap_sampling=False)
    overlapped = _short_run(mesh, 5, overlap_sampling=True)
    _assert_same_parameters(serial, overlapped)
    # The comparison can tell runs apart: one step fewer moves the weights elsewhere.
    assert not torch.equal(serial["network.hidden.0.weight"], _short_run(mesh, 4)["network.hidden.0.weight"])


def test_batches_prepared_on_the_drawing_thread_train_the_same_model(monkeypatch):
    """LSNIF's voxel walk and network-ray selection, computed with each batch on the thread that
    draws it (`prepare_training_batch`), train the same parameters as computed inside the step."""
    mesh = sphere(2)
    threads = []
    prepare = LSNIFModel.prepare_training_batch

    def spy(self, rays):
        threads.append(threading.current_thread().name)
        return prepare(self, rays)

    monkeypatch.setattr(LSNIFModel, "prepare_training_batch", spy)
    ahead = _short_run(mesh, 5)
    assert len(threads) == 5 and all(name.startswith("neuralrt-batches") for name in threads[1:])

    def inside_the_step(model):
        model.prepare_training_batch = lambda rays: None  # the loop hands nothing: the step computes it

    inside = _short_run(mesh, 5, on_model=inside_the_step)
    assert len(threads) == 5
    _assert_same_parameters(ahead, inside)


def test_interrupted_overlapped_run_resumes_bit_exact(tmp_path):
    """A run stopped after its step-3 checkpoint resumes to the uninterrupted run's parameters:
    the checkpoint holds the sampler state before batch 3, not one batch ahead."""
    mesh = sphere(2)
    straight = _short_run(mesh, 6)
    ckpt = tmp_path / "run.nrt"

    def stop_at_4(step, optimizer):
        if step == 4:
            raise KeyboardInterrupt

    try:
        _short_run(mesh, 6, checkpoint=ckpt, checkpoint_every=3, on_step=stop_at_4)
    except KeyboardInterrupt:
        pass
    resumed = _short_run(mesh, 6, checkpoint=ckpt, checkpoint_every=3, resume=True)
    _assert_same_parameters(straight, resumed)


def test_resuming_a_finished_run_keeps_its_record(tmp_path):
    """A run whose checkpoint is already at its last step (the model file was lost after training)
    trains nothing on resume and keeps the checkpoint's loss, accuracy and statistics."""
    mesh = sphere(2)
    ckpt = tmp_path / "run.nrt"

    def run(resume):
        model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq"))
        rays = BoxRayDistribution(MeshBLAS(mesh), model.box, pool_size=1024, seed=0)
        record = train_model(model, rays, steps=4, batch_size=256, learning_rate=0.01, progress=False,
                             checkpoint=ckpt, checkpoint_every=2, resume=resume)
        return model.state_dict(), record

    first_params, first = run(resume=False)
    again_params, again = run(resume=True)
    _assert_same_parameters(first_params, again_params)
    assert again.steps == 4 and again.resumed_from == 4
    assert again.final_loss == first.final_loss and again.final_loss == again.final_loss  # not NaN
    assert again.hit_accuracy == first.hit_accuracy and again.final_losses == first.final_losses
    assert again.extra == first.extra and set(again.extra) == {"truncated_fraction"}


def test_model_dependent_sampler_is_not_drawn_ahead():
    """Samplers without ``model_independent`` (N-BVH's follow the model) are drawn on the loop's thread, in turn."""
    mesh = sphere(2)
    model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq"))
    inner = BoxRayDistribution(MeshBLAS(mesh), model.box, pool_size=1024, seed=0)
    events = []

    class FollowsModel:
        def sample(self, n):
            events.append(("sample", threading.current_thread() is threading.main_thread()))
            return inner.sample(n)

    train_model(model, FollowsModel(), steps=3, batch_size=256, learning_rate=0.01, progress=False,
                on_step=lambda step, opt: events.append(("step", step)))
    assert events == [("sample", True), ("step", 0), ("sample", True), ("step", 1), ("sample", True), ("step", 2)]


class _Recorded:
    """A model-independent sampler that records the drawing thread's scheduling policy."""

    model_independent = True

    def __init__(self, delay: float = 0.0):
        self.delay, self.policies, self.threads = delay, [], []

    def sample(self, n):
        self.policies.append(os.sched_getscheduler(0) if hasattr(os, "sched_getscheduler") else None)
        self.threads.append(threading.get_ident())
        time.sleep(self.delay)
        return n


@pytest.mark.skipif(not prefetch.IDLE_PRIORITY, reason="no SCHED_IDLE on this OS")
def test_batches_are_drawn_at_idle_priority_until_the_step_starves():
    """The drawing thread runs at idle priority, so it takes no core from the step's parallel
    regions; when the step keeps waiting for batches (here a sampler slower than the step), later
    batches come from a fresh thread of normal priority, and the batches stay the same, in order."""
    fast = _Recorded()
    source = prefetch.BatchSource(fast, 8, overlap=True)
    assert [source.next(ahead=True)[0] for _ in range(5)] == [8] * 5
    source.close()
    assert fast.policies[0] == os.sched_getscheduler(0) != os.SCHED_IDLE  # the first batch: the loop's thread
    assert set(fast.policies[1:]) == {os.SCHED_IDLE} and len(set(fast.threads[1:])) == 1

    slow = _Recorded(delay=0.004)
    source = prefetch.BatchSource(slow, 8, overlap=True)
    windows = prefetch.STARVED_WINDOWS
    for _ in range((windows + 1) * prefetch._WINDOW):
        assert source.next(ahead=True)[0] == 8  # the step takes no time: all of it is waiting
    source.close()
    assert not source.idle_priority
    starved = slow.policies.index(os.sched_getscheduler(0), 1)  # the first batch back at normal priority
    assert set(slow.policies[1:starved]) == {os.SCHED_IDLE}
    assert windows * prefetch._WINDOW <= starved <= windows * prefetch._WINDOW + 2  # not before the last starved window
    assert set(slow.policies[starved:]) == {os.sched_getscheduler(0)} and slow.threads[starved] != slow.threads[1]


@pytest.mark.skipif(not prefetch.IDLE_PRIORITY, reason="no SCHED_IDLE on this OS")
def test_one_starved_window_keeps_idle_priority(monkeypatch):
    """A single window of waiting (a brief hiccup of the machine) leaves the thread at idle
    priority: only STARVED_WINDOWS starved windows in a row give it up."""
    sampler = _Recorded()
    source = prefetch.BatchSource(sampler, 8, overlap=True)
    # One window of batches far slower than the step (a 4 ms step), then batches that take no time.
    delays = iter([0.02] * prefetch._WINDOW + [0.0] * (prefetch.STARVED_WINDOWS * prefetch._WINDOW))
    monkeypatch.setattr(sampler, "sample", lambda n, _sample=sampler.sample: (time.sleep(next(delays, 0.0)), _sample(n))[1])
    for _ in range((prefetch.STARVED_WINDOWS + 1) * prefetch._WINDOW):
        assert source.next(ahead=True)[0] == 8
        time.sleep(0.004)  # the step
    source.close()
    assert source._starved_windows == 0  # the first window was starved, the later ones not
    assert source.idle_priority and set(sampler.policies[1:]) == {os.SCHED_IDLE}


def test_idle_priority_can_be_turned_off():
    recorded = _Recorded()
    source = prefetch.BatchSource(recorded, 4, overlap=True, idle_priority=False)
    for _ in range(3):
        source.next(ahead=True)
    source.close()
    assert len(set(recorded.policies)) == 1


def _trial_modes(seconds_per_step, steps):
    """The modes an `_OverlapTrial` gives over ``steps`` steps, each step taking
    ``seconds_per_step(step, mode, changed)`` (``changed``: its mode is not the previous step's);
    and its choice after each step."""
    trial, now, modes, choices = prefetch._OverlapTrial(), 0.0, [], []
    for step in range(steps):
        mode = trial.mode(now)
        now += seconds_per_step(step, mode, bool(modes) and mode != modes[-1])
        modes.append(mode)
        choices.append(trial.choice)
    return modes, choices


def _changed_slow(fast_mode):
    """Steps of ``fast_mode`` 1 ms, of the other 1.2 ms; a change of mode (a batch drawn twice or
    not at all) 1 s drawing ahead, none in turn."""
    def seconds(step, mode, changed):
        if changed:
            return 1.0 if mode else 0.0
        return 0.001 if mode == fast_mode else 0.0012
    return seconds


TRIAL_STEPS = prefetch.TRIAL_START + 2 * prefetch.TRIAL_ROUNDS * prefetch.TRIAL_WINDOW


@pytest.mark.parametrize("ahead_faster", [False, True])
def test_the_overlap_trial_keeps_the_faster_mode(ahead_faster):
    """Warm-up steps drawn ahead, then windows drawn in turn and ahead alternating, then the faster
    mode, with a window of the other mode and one of the faster at the end of every
    `RECHECK_EVERY` steps; the first step of each window (a change of mode) is not timed, so a
    slow first step does not decide, and the rechecks keep the choice."""
    every, window = prefetch.RECHECK_EVERY, prefetch.TRIAL_WINDOW
    modes, choices = _trial_modes(_changed_slow(ahead_faster), TRIAL_STEPS + 3 * every)
    start = prefetch.TRIAL_START
    assert modes[:start] == [True] * start
    for w in range(2 * prefetch.TRIAL_ROUNDS):  # in turn first
        assert modes[start + w * window: start + (w + 1) * window] == [w % 2 == 1] * window
    assert choices[:TRIAL_STEPS] == [None] * TRIAL_STEPS and set(choices[TRIAL_STEPS:]) == {ahead_faster}
    recheck = [not ahead_faster] * window + [ahead_faster] * window
    for period in range(3):
        first = TRIAL_STEPS + period * every
        assert modes[first: first + every] == [ahead_faster] * (every - 2 * window) + recheck


@pytest.mark.parametrize("ahead_faster_later", [False, True])
def test_the_overlap_rechecks_follow_a_change_of_the_machine(ahead_faster_later):
    """A machine that favoured one mode during the trial and the other after it: the rechecks
    change the choice once half or more of the last `TRIAL_ROUNDS` windows of each mode are of
    the new machine, and keep it."""
    trial_only = _changed_slow(not ahead_faster_later)
    later = _changed_slow(ahead_faster_later)
    every = prefetch.RECHECK_EVERY
    steps = TRIAL_STEPS + (prefetch.TRIAL_ROUNDS + 2) * every
    modes, choices = _trial_modes(lambda step, *a: (trial_only if step < TRIAL_STEPS else later)(step, *a), steps)
    assert choices[TRIAL_STEPS] is (not ahead_faster_later)
    changed = choices.index(ahead_faster_later)  # the step after the recheck that changed it
    assert (changed - TRIAL_STEPS) % every == 0
    # half the windows of each mode (medians tied but for rounding) or a majority
    assert (changed - TRIAL_STEPS) // every in (prefetch.TRIAL_ROUNDS // 2, prefetch.TRIAL_ROUNDS // 2 + 1)
    assert set(choices[changed:]) == {ahead_faster_later}
    kept = every - 2 * prefetch.TRIAL_WINDOW  # the steps of a period before its recheck
    assert modes[changed: changed + kept] == [ahead_faster_later] * kept


@pytest.mark.parametrize("ahead_gain, changes", [(0.01, False), (0.05, True)])
def test_a_recheck_changes_the_mode_only_past_the_margin(ahead_gain, changes):
    """After the trial chose drawing in turn, a machine where drawing ahead is faster by less than
    `RECHECK_MARGIN` keeps it (noise must not flip the mode), by more changes it."""
    assert prefetch.RECHECK_MARGIN == 0.02
    trial_only = _changed_slow(False)

    def later(step, mode, changed):
        if changed:
            return 1.0 if mode else 0.0
        return 0.001 * (1 - ahead_gain) if mode else 0.001

    steps = TRIAL_STEPS + (prefetch.TRIAL_ROUNDS + 2) * prefetch.RECHECK_EVERY
    _, choices = _trial_modes(lambda step, *a: (trial_only if step < TRIAL_STEPS else later)(step, *a), steps)
    assert choices[TRIAL_STEPS] is False and (True in choices) is changes


def test_batch_source_trial_keeps_the_batches_in_order():
    """With the default overlap (the trial), the batches come in the sampler's order whatever the
    mode of each step, no drawing thread is left while steps draw in turn, and `draws_ahead` is
    None until the trial decides."""
    class Counting:
        model_independent = True

        def __init__(self):
            self.drawn = 0

        def sample(self, n):
            self.drawn += 1
            return self.drawn

    source = prefetch.BatchSource(Counting(), 8)
    steps = prefetch.TRIAL_START + 2 * prefetch.TRIAL_ROUNDS * prefetch.TRIAL_WINDOW
    got = []
    for step in range(steps):
        got.append(source.next(ahead=True)[0])
        assert source.draws_ahead is None
        in_turn = step >= prefetch.TRIAL_START and (step - prefetch.TRIAL_START) // prefetch.TRIAL_WINDOW % 2 == 0
        # drawing in turn ends the drawing thread (its OpenMP threads would slow the step's regions)
        assert (source._executor is None) == in_turn
    got += [source.next(ahead=True)[0] for _ in range(5)]
    source.close()
    assert got == list(range(1, steps + 6)) and isinstance(source.draws_ahead, bool)
    assert prefetch.BatchSource(Counting(), 8, overlap=False).draws_ahead is False


@pytest.fixture(scope="module")
def checkpointed(tmp_path_factory):
    """(mesh, config, checkpoint path) of a 2-step LSNIF run that saved a checkpoint."""
    from neuralrt.training.api import train

    mesh, folder = sphere(2), tmp_path_factory.mktemp("ckpt")
    config = LSNIFConfig.preset("lq").with_training(steps=2, batch_size=256)
    train(mesh, config, progress=False, checkpoint=folder / "m.ckpt")
    return mesh, config, folder / "m.ckpt"


def _edited_checkpoint(path, out, change):
    from neuralrt.io.model_file import read_model_file, write_model_file

    f = read_model_file(path)
    header = {k: v for k, v in f.header.items() if k not in ("format_version", "method", "arrays_sha256")}
    change(header)
    write_model_file(out, f.method, header, f.arrays)  # well formed, checksums right
    return out


@pytest.mark.parametrize("change, message", [
    # (as Python spells it: the API caller was told "--resume")
    (lambda h: h.pop("optimizer"), r"cannot resume from this checkpoint \(KeyError: 'optimizer'\); delete it or drop resume=True"),
    (lambda h: h.update(step=-1), r"corrupted checkpoint \(step -1\); delete it or drop resume=True"),
    (lambda h: h["record"].update(unknown=1), r"cannot resume from this checkpoint \(ValueError: its record: unknown: Unexpected keyword"),
    # the record was copied into the model as it stood
    (lambda h: h["record"].update(steps="many"), r"\(ValueError: its record: steps: Input should be a valid integer \(got 'many'\)\)"),
    (lambda h: h["record"].update(seconds=-1.0), r"its record: seconds: Input should be greater than or equal to 0 \(got -1.0\)"),
    (lambda h: h.update(record=[1]), r"\(ValueError: its record is a list, not a table\)"),
    (lambda h: h["optimizer"]["param_groups"][0]["params"].reverse(), r"cannot resume from this checkpoint \(ValueError: Adam's exp_avg has shape"),
    # (a TypeError inside Adam's first step, after the set-up)
    (lambda h: h["optimizer"]["param_groups"][0].update(betas="ab"), r"\(ValueError: Adam's betas is 'ab', not a value like"),
    (lambda h: h["optimizer"]["param_groups"][0].update(lr=None), r"\(ValueError: Adam's lr is None, not a value like"),
    # (from a fuzzing trial: a KeyError inside Adam's step, a RuntimeError, a run trained uphill; a step of 1e30)
    (lambda h: h["optimizer"]["param_groups"][0].update(amsgrad=True), r"\(ValueError: Adam's amsgrad is True, this run's False\)"),
    (lambda h: h["optimizer"]["param_groups"][0].update(maximize=True), r"\(ValueError: Adam's maximize is True, this run's False\)"),
    (lambda h: h.update(step=10**30), r"corrupted checkpoint \(step 10{30}\)"),
    (lambda h: h["sampler"].update(pool_cursor=-7), r"\(ValueError: its pool cursor -7 is not a slot of its pool of"),
])
def test_a_checkpoint_that_cannot_be_resumed_is_one_line(checkpointed, tmp_path, change, message):
    # Each was a traceback (KeyError, TypeError, ...) from deep in the restore.
    from neuralrt.errors import ModelFileError
    from neuralrt.training.api import train

    mesh, config, path = checkpointed
    bad = _edited_checkpoint(path, tmp_path / "bad.ckpt", change)
    with pytest.raises(ModelFileError, match=message):
        train(mesh, config.with_training(steps=4), progress=False, checkpoint=bad, resume=True)


def test_a_truncated_checkpoint_is_told_before_the_set_up(checkpointed, tmp_path, monkeypatch):
    from neuralrt.errors import ModelFileError
    from neuralrt.training.api import train

    mesh, config, path = checkpointed
    (tmp_path / "cut.ckpt").write_bytes(path.read_bytes()[:-100])

    def no_set_up(*args, **kwargs):
        raise AssertionError("the model was built before the checkpoint was checked")

    monkeypatch.setattr(LSNIFModel, "from_mesh", no_set_up)
    with pytest.raises(ModelFileError, match="truncated"):
        train(mesh, config.with_training(steps=4), progress=False, checkpoint=tmp_path / "cut.ckpt", resume=True)


def _edited_checkpoint_arrays(path, out, change):
    from neuralrt.io.model_file import read_model_file, write_model_file

    f = read_model_file(path)
    arrays = dict(f.arrays)
    change(arrays)
    write_model_file(out, f.method, {k: v for k, v in f.header.items() if k not in ("format_version", "method")}, arrays)
    return out


def test_a_checkpoint_whose_model_state_is_nan_is_refused(checkpointed, tmp_path):
    # It resumed and wrote a model that no one could load.
    from neuralrt.errors import ModelFileError
    from neuralrt.training.api import train

    mesh, config, path = checkpointed
    bad = _edited_checkpoint_arrays(path, tmp_path / "nan.ckpt", lambda a: a["model.network.output.bias"].fill_(float("nan")))
    with pytest.raises(ModelFileError, match=r"network\.output\.bias holds NaN or infinite values"):
        train(mesh, config.with_training(steps=4), progress=False, checkpoint=bad, resume=True)


@pytest.mark.parametrize("change, message", [
    # (a pool of points longer than its normals: a segmentation fault in the pool's kernels)
    (lambda a: a.update({"sampler.pool_points": a["sampler.pool_points"].repeat(4, 1)}), r"its surface pool is \[\d+, 3\] points and"),
    (lambda a: a.update({"sampler.pool_normals": a["sampler.pool_normals"][:10].clone()}), r"its surface pool is .* and \[10, 3\] normals"),
    (lambda a: a.update({"sampler.pool_points": a["sampler.pool_points"][:0].clone(),
                         "sampler.pool_normals": a["sampler.pool_normals"][:0].clone()}), r"its surface pool is \[0, 3\] points"),
    (lambda a: a["sampler.pool_points"].fill_(float("nan")), "its surface pool holds numbers that are not finite"),
    (lambda a: a["sampler.pool_normals"].zero_(), "its surface pool holds .* or zero normals"),
    (lambda a: a.update({k: -v for k, v in a.items() if k.endswith("exp_avg_sq")}), r"Adam's exp_avg_sq holds negative values"),
])
def test_a_checkpoint_whose_arrays_no_run_saves_is_refused(checkpointed, tmp_path, change, message):
    from neuralrt.errors import ModelFileError
    from neuralrt.training.api import train

    mesh, config, path = checkpointed
    bad = _edited_checkpoint_arrays(path, tmp_path / "bad.ckpt", change)
    with pytest.raises(ModelFileError, match=r"cannot resume from this checkpoint \(ValueError: " + message):
        train(mesh, config.with_training(steps=4), progress=False, checkpoint=bad, resume=True)


def test_an_nbvh_checkpoint_whose_tree_cannot_be_walked_is_refused(tmp_path):
    # Its tree is indexed unchecked as a model file's is: an out-of-range child was an IndexError traceback.
    from neuralrt.errors import ModelFileError
    from neuralrt.methods.nbvh_config import NBVHConfig
    from neuralrt.training.api import train

    mesh = sphere(2)
    config = NBVHConfig.preset("cpu").with_training(steps=2, batch_size=256)
    train(mesh, config, progress=False, checkpoint=tmp_path / "n.ckpt")

    def far_child(arrays):
        children = arrays["model.node_children"]
        children[children[:, 0] >= 0] = torch.tensor([10**8, 10**8 + 1], dtype=children.dtype)

    bad = _edited_checkpoint_arrays(tmp_path / "n.ckpt", tmp_path / "bad.ckpt", far_child)
    with pytest.raises(ModelFileError, match=r"cannot resume from this checkpoint \(ValueError: the tree's child indices"):
        train(mesh, config, progress=False, checkpoint=bad, resume=True)


@pytest.mark.parametrize("change, message", [
    (lambda a: a.pop(next(k for k in a if k.endswith(".exp_avg"))), r"Adam's state of a parameter lacks exp_avg"),
    (lambda a: a[next(k for k in a if k.endswith(".exp_avg_sq"))].fill_(float("nan")), r"Adam's exp_avg_sq holds NaN"),
])
def test_a_checkpoint_whose_optimizer_state_is_incomplete_or_nan_is_refused(checkpointed, tmp_path, change, message):
    # A missing moment was a KeyError traceback from inside Adam's first step after the resume.
    from neuralrt.errors import ModelFileError
    from neuralrt.training.api import train

    mesh, config, path = checkpointed
    bad = _edited_checkpoint_arrays(path, tmp_path / "adam.ckpt", change)
    with pytest.raises(ModelFileError, match=message):
        train(mesh, config.with_training(steps=4), progress=False, checkpoint=bad, resume=True)
