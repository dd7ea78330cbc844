"""The training curve: bins of any run length, means over the right steps, resume, stored form."""

import math

import pytest

from neuralrt.training.curve import MAX_POINTS, TrainingCurve, curve_problem


def _loss(step):  # a loss that differs at every step, so a wrong bin shows
    return 1.0 / step + 0.001 * (step % 7)


def _feed(curve, first, last):
    for step in range(first, last + 1):
        curve.add(step, 0.01 * step, _loss(step), correct=step % 5, count=4,
                  losses={"occlusion": 2 * _loss(step), "distance": step})


def _bins(stored):
    """(first step, last step) of each stored point."""
    ends = stored["step"]
    return list(zip([stored["start"] + 1, *[e + 1 for e in ends[:-1]]], ends))


@pytest.mark.parametrize("steps", [1, 7, 255, 256, 257, 1000, 10_000, 66_000])
def test_every_point_is_the_mean_over_its_bin(steps):
    curve = TrainingCurve()
    _feed(curve, 1, steps)
    curve.close()
    stored = curve.as_dict()
    if steps < 2 * MAX_POINTS:
        assert len(stored["step"]) == steps and stored["every"] == 1
    else:
        assert MAX_POINTS <= len(stored["step"]) < 2 * MAX_POINTS and stored["every"] > 1
    assert stored["every"] & (stored["every"] - 1) == 0 and stored["step"][-1] == steps
    for i, (a, b) in enumerate(_bins(stored)):
        assert b - a + 1 <= stored["every"]
        mean = sum(_loss(s) for s in range(a, b + 1)) / (b - a + 1)
        assert stored["loss"][i] == pytest.approx(mean, rel=1e-5)
        assert stored["losses"]["occlusion"][i] == pytest.approx(2 * mean, rel=1e-5)
        assert stored["losses"]["distance"][i] == pytest.approx((a + b) / 2, rel=1e-5)
        assert stored["hit_accuracy"][i] == pytest.approx(sum(s % 5 for s in range(a, b + 1)) / (4 * (b - a + 1)), rel=1e-5)
        assert stored["seconds"][i] == pytest.approx(0.01 * b)


@pytest.mark.parametrize("split", [1, 3, 4, 255, 256, 300, 511, 512, 513, 999])
def test_a_resumed_curve_is_the_uninterrupted_one(split):
    """A checkpoint's curve (with its open bin) continued gives the same points as one run."""
    straight = TrainingCurve()
    _feed(straight, 1, 1000)
    straight.close()
    first = TrainingCurve()
    _feed(first, 1, split)
    saved = first.as_dict(checkpoint=True)
    second = TrainingCurve.from_dict(saved, start=split)
    _feed(second, split + 1, 1000)
    second.close()
    assert second.as_dict() == straight.as_dict()
    assert "open" not in second.as_dict() and curve_problem(saved) is None


def test_a_curve_begun_mid_run_weighs_its_first_bin_by_its_own_steps():
    """A run resumed from a checkpoint kept before curves existed starts its curve at that step."""
    curve = TrainingCurve.from_dict({}, start=100)
    _feed(curve, 101, 2000)
    curve.close()
    stored = curve.as_dict()
    assert stored["start"] == 100 and _bins(stored)[0][0] == 101
    for i, (a, b) in enumerate(_bins(stored)):
        assert stored["loss"][i] == pytest.approx(sum(_loss(s) for s in range(a, b + 1)) / (b - a + 1), rel=1e-5)


def test_a_run_given_more_steps_keeps_its_short_last_bin_exact():
    curve = TrainingCurve()
    _feed(curve, 1, 301)  # ends with a short bin (301 is odd: bins are 2 wide by then)
    curve.close()
    more = TrainingCurve.from_dict(curve.as_dict(), start=301)
    _feed(more, 302, 5000)
    more.close()
    stored = more.as_dict()
    for i, (a, b) in enumerate(_bins(stored)):
        assert stored["loss"][i] == pytest.approx(sum(_loss(s) for s in range(a, b + 1)) / (b - a + 1), rel=1e-5)


@pytest.mark.parametrize("change, problem", [
    (lambda c: c.update(every=0), "bin width"),
    (lambda c: c.update(every=True), "bin width"),
    (lambda c: c.update(start=-1), "start"),
    (lambda c: c["loss"].pop(), "differ in length"),
    (lambda c: c["losses"]["occlusion"].pop(), "differ in length"),
    (lambda c: c.update(seconds="x"), "not a list"),
    (lambda c: c["loss"].__setitem__(0, "1"), "not a number"),
    (lambda c: c["step"].reverse(), "not increasing"),
    (lambda c: c["step"].__setitem__(0, 0.5), "not increasing"),
    (lambda c: c.update(open={"steps": 1}), "open bin"),
    (lambda c: c.update(open={"steps": "1", "loss": 0.5, "correct": 1, "count": 2, "losses": {}, "end": 21, "seconds": 1.0}),
     "open bin"),
    (lambda c: c.update(open={"steps": 1, "loss": 0.5, "correct": 1, "count": 2, "losses": {"a": None}, "end": 21,
                              "seconds": 1.0}), "open bin"),
])
def test_a_malformed_curve_is_named(change, problem):
    from neuralrt.training.trainer import TrainingRecord

    curve = TrainingCurve()
    _feed(curve, 1, 20)
    stored = curve.as_dict()
    assert curve_problem(stored) is None and curve_problem({}) is None
    change(stored)
    assert problem in curve_problem(stored)
    with pytest.raises(ValueError, match=f"curve: .*{problem}"):
        TrainingRecord(curve=stored)
    assert "table" in curve_problem([1, 2])


def test_nan_accuracy_where_a_bin_saw_no_rays():
    curve = TrainingCurve()
    curve.add(1, 0.1, 0.5, correct=0, count=0, losses={})
    assert math.isnan(curve.as_dict()["hit_accuracy"][0])
