"""Compute precision: "auto" is decided once per process and recorded; MLP answers in bf16 vs fp32."""

import builtins

import torch

from neuralrt.geometry.procedural import sphere
from neuralrt.methods import lsnif_fused_cpu
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel
from neuralrt.neural import precision
from neuralrt.rays import Rays


def test_auto_reads_the_cpu_flags_once_per_process(monkeypatch):
    opened = []
    real_open = builtins.open

    def counting_open(file, *args, **kwargs):
        if str(file) == "/proc/cpuinfo":
            opened.append(file)
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", counting_open)
    precision.cpu_has_native_bf16.cache_clear()
    try:
        config = LSNIFConfig.preset("lq", inference={"chunk_size": 64})
        model = LSNIFModel.from_mesh(sphere(2), config)
        g = torch.Generator().manual_seed(0)
        o = torch.randn(1000, 3, generator=g) * 3
        monkeypatch.setattr(lsnif_fused_cpu, "MIN_RAYS_PER_THREAD", 0)
        model.intersect(Rays(o, -o))  # 16 chunks
        model.intersect(Rays(o, -o))
        assert model.compute_dtype(training=True) in (torch.bfloat16, torch.float32)
        assert len(opened) == 1
    finally:
        precision.cpu_has_native_bf16.cache_clear()


def test_explicit_choices():
    assert precision.compute_dtype("fp32", "cpu") == torch.float32
    assert precision.compute_dtype("bf16", "cpu") == torch.bfloat16
    assert precision.compute_dtype("auto", "cuda") == torch.bfloat16
    assert precision.precision_name(torch.bfloat16) == "bf16"
