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
