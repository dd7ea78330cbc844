"""The wavefront random streams (`neuralrt.render.rng`): the numba stream is torch's CPU generator's
stream bit for bit, across seeds wider than 32 bits and draws that split the 624-word blocks."""

import numpy as np
import pytest
import torch

from neuralrt.render.rng import NumbaUniforms, TorchUniforms


@pytest.mark.parametrize("seed", [0, 1, 123, 2**32 + 7, 123456789012, 2**63 + 5])
def test_numba_stream_equals_torch_generator(seed):
    ref, got = TorchUniforms(seed, "cpu"), NumbaUniforms(seed)
    # Shapes that end inside, at and across block boundaries, one much larger than a block.
    for shape in [(5, 2), (1,), (617,), (624,), (1000, 8), (7,), (40000, 8), (3, 0), (1249,)]:
        a, b = ref.uniform(shape), got.uniform(shape)
        assert b.dtype == torch.float32 and b.shape == a.shape
        assert torch.equal(a, b), (seed, shape)


def test_numba_stream_is_a_fresh_stream_per_seed():
    a = NumbaUniforms(5).uniform((64,))
    assert torch.equal(a, NumbaUniforms(5).uniform((64,)))
    assert not torch.equal(a, NumbaUniforms(6).uniform((64,)))
    assert float(a.min()) >= 0.0 and float(a.max()) < 1.0
    assert np.unique(a.numpy()).size == 64


def test_wavefront_seeds_depend_on_every_seed_bit_and_do_not_alias():
    from neuralrt.render.rng import wavefront_seed

    # seed * 1_000_003 + wavefront (as before) kept only the low 32 bits and made seed
    # 2021759595's first wavefront seed 0's second.
    assert wavefront_seed(2**40, 0) != wavefront_seed(0, 0) and wavefront_seed(5 + 3 * 2**32, 0) != wavefront_seed(5, 0)
    assert wavefront_seed(2021759595, 0) != wavefront_seed(0, 1)
    grid = {wavefront_seed(s, w) for s in range(200) for w in range(200)}
    assert len(grid) == 200 * 200 and all(0 <= v < 2**32 for v in grid)  # (a chance collision: ~0.4 in 40,000)
    assert wavefront_seed(7, 3) == wavefront_seed(7, 3)


def test_renders_at_seeds_equal_modulo_2_to_the_32_differ():
    from neuralrt.render.integrator import render
    from neuralrt.scene.loader import load_scene

    scene = load_scene("builtin:cornell-statue?detail=0", resolution=(8, 8))
    a, b = (render(scene, spp=2, seed=s, progress=False).image for s in (0, 2**40))
    assert not np.array_equal(a, b)
    assert np.array_equal(a, render(scene, spp=2, seed=0, progress=False).image)
