"""MC dropout: only dropout is stochastic, the encoder runs once, and the statistics are well formed."""

from __future__ import annotations

import math

import pytest
import torch

from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net
from aerialmtl.models.mc_dropout import mc_dropout_mode, mc_predict

SMALL = dict(growth_rate=12, block_config=(2, 4, 8, 6), num_init_features=32)
K = 4


def _model(dropout: float = 0.5, **kw: object) -> D3Net:
    torch.manual_seed(0)
    model = D3Net(ModelConfig(num_classes=K, dropout=dropout, **SMALL, **kw))  # type: ignore[arg-type]
    # A few training steps so that BatchNorm running stats are not the defaults.
    model.train()
    with torch.no_grad():
        for _ in range(2):
            model(torch.randn(2, 3, 64, 64))
    return model


def test_mode_switches_only_dropout_and_restores() -> None:
    model = _model()
    model.train()
    with mc_dropout_mode(model):
        for m in model.modules():
            if isinstance(m, torch.nn.Dropout):
                assert m.training
            elif isinstance(m, torch.nn.BatchNorm2d):
                assert not m.training
    assert all(m.training for m in model.modules())
    model.eval()
    with mc_dropout_mode(model):
        pass
    assert not any(m.training for m in model.modules())


def test_samples_vary_with_dropout_and_batchnorm_stats_are_unchanged() -> None:
    model = _model().eval()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    x = torch.randn(1, 3, 64, 64)
    r = mc_predict(model, x, samples=6, sample_batch=4, seed=1)
    assert (r["height"]["std"] > 0).float().mean() > 0.5
    assert r["classes"]["mutual_info"].max() > 0
    for k, v in model.state_dict().items():
        assert torch.equal(v, before[k]), f"{k} changed during mc_predict"
    assert not model.training


def test_seed_makes_sampling_reproducible() -> None:
    model = _model().eval()
    x = torch.randn(1, 3, 64, 64)
    a = mc_predict(model, x, samples=3, seed=5)
    b = mc_predict(model, x, samples=3, seed=5)
    torch.testing.assert_close(a["height"]["std"], b["height"]["std"], rtol=0, atol=0)


def test_no_dropout_is_deterministic() -> None:
    model = _model(dropout=0.0).eval()
    x = torch.randn(2, 3, 64, 64)
    r = mc_predict(model, x, samples=5, sample_batch=2)
    assert torch.allclose(r["height"]["std"], torch.zeros(()), atol=1e-5)
    assert torch.allclose(r["classes"]["mutual_info"], torch.zeros(()), atol=1e-5)
    with torch.no_grad():
        ref = model(x)
    torch.testing.assert_close(r["height"]["mean"], ref["height"], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(r["classes"]["probs"], torch.softmax(ref["classes"], 1), rtol=1e-4, atol=1e-5)


def test_single_sample_has_zero_spread() -> None:
    model = _model().eval()
    r = mc_predict(model, torch.randn(1, 3, 64, 64), samples=1)
    assert torch.count_nonzero(r["height"]["std"]) == 0
    assert torch.count_nonzero(r["classes"]["mutual_info"]) == 0
    assert r["classes"]["entropy"].min() > 0


def test_encoder_runs_once_per_call() -> None:
    model = _model().eval()
    calls = []
    handle = model.encoder.register_forward_hook(lambda *_: calls.append(1))
    try:
        mc_predict(model, torch.randn(2, 3, 64, 64), samples=7, sample_batch=3)
    finally:
        handle.remove()
    assert len(calls) == 1


@pytest.mark.parametrize("sample_batch", [None, 2])
def test_statistics_shapes_and_bounds(sample_batch: int | None) -> None:
    model = _model().eval()
    x = torch.randn(2, 3, 64, 96)
    r = mc_predict(model, x, samples=5, sample_batch=sample_batch, seed=0)
    h, c = r["height"], r["classes"]
    assert h["mean"].shape == h["std"].shape == (2, 1, 64, 96)
    assert c["probs"].shape == (2, K, 64, 96)
    assert c["entropy"].shape == c["mutual_info"].shape == (2, 64, 96)
    assert all(v.dtype == torch.float32 for d in r.values() for v in d.values())
    assert (h["std"] >= 0).all()
    torch.testing.assert_close(c["probs"].sum(1), torch.ones(2, 64, 96))
    assert (c["entropy"] >= 0).all() and (c["entropy"] <= math.log(K) + 1e-5).all()
    assert (c["mutual_info"] >= 0).all() and (c["mutual_info"] <= c["entropy"] + 1e-6).all()


def test_chunked_std_matches_direct_std() -> None:
    """The chunk-combined (Welford/Chan) std equals the std of the same samples taken directly."""
    model = _model().eval()
    x = torch.randn(1, 3, 64, 64)
    r = mc_predict(model, x, samples=5, sample_batch=2, seed=3)
    torch.manual_seed(3)
    with mc_dropout_mode(model), torch.no_grad():
        feats = model.encode(x)
        draws = []
        for s in (2, 2, 1):  # the same chunks, hence the same dropout masks
            out = model.decode([f.repeat(s, 1, 1, 1) for f in feats])["height"]
            draws.append(out)
    hs = torch.cat(draws).double()
    torch.testing.assert_close(r["height"]["mean"].double(), hs.mean(0, keepdim=True), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(r["height"]["std"].double(), hs.std(0, unbiased=False, keepdim=True),
                               rtol=1e-4, atol=1e-6)


def test_single_task_and_bf16_autocast() -> None:
    model = _model(tasks=("classes",)).eval()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        r = mc_predict(model, torch.randn(1, 3, 64, 64), samples=3, seed=0)
    assert set(r) == {"classes"}
    assert r["classes"]["probs"].dtype == torch.float32
    assert torch.isfinite(r["classes"]["entropy"]).all()


@pytest.mark.parametrize("head", [{}, {"aleatoric": True}, {"aleatoric": True, "height_bins": 8}])
def test_decoding_the_height_task_alone_gives_its_statistics_to_the_bit(head: dict) -> None:
    """What calibration asks for (only the heights): the classes' blocks are not run, and the height mean, spread
    (and aleatoric spread) are those of the full decode with the same masks, to the bit (the dropout layers are
    all in the shared blocks)."""
    model = _model(**head).eval()
    x = torch.randn(2, 3, 64, 64)
    full = mc_predict(model, x, samples=4, seed=3)
    alone = mc_predict(model, x, samples=4, seed=3, tasks=("height",))
    assert set(full) == {"height", "classes"} and set(alone) == {"height"}
    assert set(alone["height"]) == set(full["height"]) and len(full["height"]) == (3 if head else 2)
    for name, value in full["height"].items():
        torch.testing.assert_close(alone["height"][name], value, rtol=0, atol=0)


def test_samples_must_be_positive() -> None:
    with pytest.raises(ValueError, match="samples"):
        mc_predict(_model(), torch.randn(1, 3, 32, 32), samples=0)


def test_keyed_masks_do_not_depend_on_batch_or_sample_chunks() -> None:
    """With keys, an image's masks come from (seed, key, sample): batch company and chunking change nothing."""
    from aerialmtl.models.mc_dropout import mc_statistics

    model = _model().eval()
    x = torch.randn(3, 3, 64, 64)
    full = mc_statistics(model, x, 5, sample_batch=5, seed=2, keys=[10, 11, 12])
    alone = mc_statistics(model, x[1:2], 5, sample_batch=2, seed=2, keys=[11])
    torch.testing.assert_close(alone.height_mean[0], full.height_mean[1], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(alone.probs[0], full.probs[1], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(alone.mean_entropy[0], full.mean_entropy[1], rtol=1e-5, atol=1e-5)
    other = mc_statistics(model, x[1:2], 5, seed=2, keys=[99])  # another window: other masks
    assert not torch.allclose(other.height_std[0], full.height_std[1], rtol=1e-2, atol=0)
    assert all(not m.training for m in model.modules())  # modes restored


@pytest.mark.parametrize("path", ["kernel", "torch"])
def test_entropy_with_one_log_per_pixel_equals_the_definition(path: str) -> None:
    from aerialmtl.models.mc_dropout import _class_sums, _class_sums_torch

    z = (torch.randn(2, 6, 9, 11) * 8).contiguous(memory_format=torch.channels_last)
    p_sum, e_sum = (_class_sums if path == "kernel" else _class_sums_torch)(z, 2, 1)
    p = torch.softmax(z.double(), 1)
    torch.testing.assert_close(p_sum[:, 0].double(), p.sum(0), rtol=1e-5, atol=1e-6)
    ent = -(p * torch.log(p.clamp_min(1e-300))).sum(1)
    torch.testing.assert_close(e_sum[0].double(), ent.sum(0), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("chunk", [1, 2, 3])
def test_class_sums_added_in_place_equal_the_sum_of_chunk_sums(chunk: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The class sums of each chunk are added into the running sums block by block (no chunk-sized array per
    call): the same bits (tolerance 0) as summing each chunk's samples apart, then adding the chunk sums; row
    blocks of a few rows, the last one shorter."""
    from aerialmtl.models import class_kernel, mc_dropout
    from aerialmtl.models.mc_dropout import _class_sums, accumulate_samples

    monkeypatch.setattr(mc_dropout, "_ROW_BLOCK_ELEMENTS", 1000)
    monkeypatch.setattr(class_kernel, "available", lambda: False)  # torch's path (CUDA, or no numba)

    samples, b = 5, 2
    z = (torch.randn(samples * b, 6, 11, 9) * 6).contiguous(memory_format=torch.channels_last)

    def decode(done: int, s: int) -> dict[str, torch.Tensor]:
        return {"classes": z[done * b:(done + s) * b]}

    stats = accumulate_samples(decode, samples, chunk, b)
    p_sum = e_sum = None
    for done in range(0, samples, chunk):
        s = min(chunk, samples - done)
        c_p, c_e = _class_sums(z[done * b:(done + s) * b], s, b)
        p_sum = c_p if p_sum is None else p_sum + c_p
        e_sum = c_e if e_sum is None else e_sum + c_e
    assert p_sum is not None and e_sum is not None and stats.probs is not None and stats.mean_entropy is not None
    assert torch.equal(stats.probs, (p_sum / samples).permute(1, 2, 3, 0))
    assert torch.equal(stats.mean_entropy, e_sum / samples)


@pytest.mark.parametrize("layout", ["planes", "channels_last"])
@pytest.mark.parametrize("k, h, w, scale", [(20, 7, 37, 6.0), (2, 5, 3, 1.0), (6, 4, 17, 60.0), (9, 3, 65, 0.0)])
def test_class_kernel_equals_torch_path(k: int, h: int, w: int, scale: float, layout: str) -> None:
    """The CPU kernel's sums (mean probabilities, per-sample entropy) are torch's to 1e-6 / 2e-6: K from 2 to 20,
    widths that are no multiple of the vector length, logits from all-equal (scale 0: p = 1/K, H = log K) to
    ±200 (probabilities of exactly 0 and 1, exp underflow), two images, sample-major; class planes and channels
    last (as OpenVINO's decoder graph and a channels-last torch model return them)."""
    from aerialmtl.models import class_kernel
    from aerialmtl.models.mc_dropout import _class_sums, _class_sums_torch

    assert class_kernel.available()
    samples, b = 3, 2
    z = torch.randn(samples * b, k, h, w, generator=torch.Generator().manual_seed(k)) * scale
    if scale:
        z[0, 0, 0, 0] = 200.0
        z[1, :, 0, 1] = -200.0
    if layout == "channels_last":
        z = z.contiguous(memory_format=torch.channels_last)
    p_k, e_k = _class_sums(z, samples, b)
    p_t, e_t = _class_sums_torch(z.contiguous(), samples, b)
    torch.testing.assert_close(p_k, p_t, rtol=0, atol=1e-6)
    torch.testing.assert_close(e_k, e_t, rtol=0, atol=2e-6)
    if scale == 0.0:
        torch.testing.assert_close(e_k, torch.full_like(e_k, samples * math.log(k)), rtol=1e-6, atol=0)


def test_class_kernel_sums_do_not_depend_on_the_chunks_and_keep_nan() -> None:
    """The kernel adds samples one by one into the running sums, so chunks of 1, 2 or 5 samples give the same bits
    (tolerance 0); a NaN logit (a broken model) gives NaN probabilities and entropy at that pixel, as torch's path
    does, so the sanity checks still see it."""
    from aerialmtl.models.mc_dropout import accumulate_samples

    samples, b = 5, 2
    z = torch.randn(samples * b, 6, 5, 19, generator=torch.Generator().manual_seed(3)) * 4
    z[3, 2, 1, 4] = float("nan")

    def decode(done: int, s: int) -> dict[str, torch.Tensor]:
        return {"classes": z[done * b:(done + s) * b]}

    runs = [accumulate_samples(decode, samples, chunk, b) for chunk in (1, 2, 5)]
    for other in runs[1:]:
        assert torch.equal(other.probs.nan_to_num(-1), runs[0].probs.nan_to_num(-1))
        assert torch.equal(other.mean_entropy.nan_to_num(-1), runs[0].mean_entropy.nan_to_num(-1))
    probs, ent = runs[0].probs, runs[0].mean_entropy
    assert probs[1, 1, 4].isnan().all() and ent[1, 1, 4].isnan()  # image 1 (row 3 = sample 1, image 1)
    assert not probs[0].isnan().any() and ent.isnan().sum() == 1


def test_class_kernel_runs_where_numba_cannot_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    """A read-only install and home: numba finds nowhere to keep the compiled kernel and refuses ``cache=True``;
    the kernel is then compiled without its cache and still runs (not an error at the first MC window)."""
    import numba
    import numba.core.caching as caching
    import numpy as np

    from aerialmtl import jit

    def add_one(x):  # noqa: ANN001, ANN202 - a function for numba
        return x + 1

    monkeypatch.setattr(caching.CacheImpl, "_locator_classes", [])
    with pytest.raises(RuntimeError, match="no locator"):
        numba.njit(cache=True)(add_one)
    assert jit.jit(add_one)(np.float32(1.0)) == 2.0
