"""Monte-Carlo dropout (Gal & Ghahramani 2016): T stochastic decoder passes → mean and spread.

Only the dropout layers are stochastic at test time; BatchNorm stays in eval mode (running statistics
used and never updated). Because every dropout layer of :class:`~aerialmtl.models.d3net.D3Net` sits in
``decode``, :func:`mc_predict` runs the encoder ONCE and repeats its features along the batch to
sample the decoder, ``sample_batch`` samples at a time.

Outputs per enabled task:

* ``height``: ``mean`` and ``std`` (B×1×H×W, metres; std is the population std over the T samples,
  the epistemic spread).
* ``classes``: ``probs`` (B×K×H×W, mean softmax), ``entropy`` (B×H×W, nats, predictive entropy
  H[mean p] ∈ [0, log K]) and ``mutual_info`` (B×H×W, nats, H[mean p] − mean_t H[p_t], clamped ≥ 0;
  the BALD epistemic part).

All statistics are accumulated in float32 (also under bf16 autocast); the height spread uses Chan's
parallel combination of per-chunk means and squared deviations (Welford), which stays stable for
heights far from zero.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from torch import nn

_DROPOUT_TYPES = (nn.Dropout, nn.Dropout1d, nn.Dropout2d, nn.Dropout3d, nn.AlphaDropout, nn.FeatureAlphaDropout)


@contextlib.contextmanager
def mc_dropout_mode(model: nn.Module) -> Iterator[nn.Module]:
    """Put ``model`` in eval mode with only its dropout modules in train mode; restore modes on exit."""
    modes = {m: m.training for m in model.modules()}
    try:
        model.eval()
        for m in model.modules():
            if isinstance(m, _DROPOUT_TYPES):
                m.train()
        yield model
    finally:
        for m, mode in modes.items():
            m.training = mode


def _entropy(p: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """Shannon entropy (nats) of probabilities ``p`` along ``dim`` (0·log 0 = 0)."""
    return -(p * torch.log(p.clamp_min(1e-12))).sum(dim)


@torch.no_grad()
def mc_predict(
    model: nn.Module,
    x: torch.Tensor,
    samples: int,
    sample_batch: int | None = None,
    seed: int | None = None,
) -> dict[str, dict[str, torch.Tensor]]:
    """MC-dropout prediction of a D3-Net-like model (with ``encode``/``decode``).

    Args:
        model: a model with ``encode(x) -> list[Tensor]`` (deterministic) and ``decode(feats) -> dict``.
        x: B×C×H×W normalised image batch.
        samples: T ≥ 1 decoder samples (T = 1 gives std 0 and mutual information 0).
        sample_batch: decode at most this many samples per pass (bounds memory: the decoder sees
            ``B·sample_batch`` images at once); default all T at once.
        seed: seed the dropout masks (the global RNG state is restored afterwards); default: the
            current global RNG.

    Returns:
        ``{"height": {"mean", "std"}, "classes": {"probs", "entropy", "mutual_info"}}`` for the tasks the
        model returns, float32 (shapes in the module docstring).
    """
    if samples < 1:
        raise ValueError(f"mc_predict: samples must be ≥ 1, got {samples}")
    chunk = samples if sample_batch is None else max(1, min(int(sample_batch), samples))
    devices = [x.device] if x.device.type == "cuda" else []
    rng = torch.random.fork_rng(devices=devices) if seed is not None else contextlib.nullcontext()
    with mc_dropout_mode(model), rng:
        if seed is not None:
            torch.manual_seed(seed)
        feats = model.encode(x)
        b = x.shape[0]
        h_mean: torch.Tensor | None = None
        h_m2: torch.Tensor | None = None
        p_sum: torch.Tensor | None = None
        ent_sum: torch.Tensor | None = None
        done = 0
        while done < samples:
            s = min(chunk, samples - done)
            rep = [f.repeat(s, 1, 1, 1) if s > 1 else f for f in feats]
            out = model.decode(rep)
            if "height" in out:
                hs = out["height"].float().unflatten(0, (s, b))  # s×B×1×H×W
                c_mean = hs.mean(0)
                c_m2 = ((hs - c_mean) ** 2).sum(0)
                if h_mean is None:
                    h_mean, h_m2 = c_mean, c_m2
                else:  # Chan et al. parallel update
                    assert h_m2 is not None
                    delta = c_mean - h_mean
                    n = done + s
                    h_mean = h_mean + delta * (s / n)
                    h_m2 = h_m2 + c_m2 + delta**2 * (done * s / n)
            if "classes" in out:
                ps = torch.softmax(out["classes"].float(), dim=1).unflatten(0, (s, b))  # s×B×K×H×W
                c_p = ps.sum(0)
                c_e = _entropy(ps, dim=2).sum(0)
                p_sum = c_p if p_sum is None else p_sum + c_p
                ent_sum = c_e if ent_sum is None else ent_sum + c_e
            done += s
    result: dict[str, dict[str, torch.Tensor]] = {}
    if h_mean is not None and h_m2 is not None:
        result["height"] = {"mean": h_mean, "std": (h_m2 / samples).clamp_min(0).sqrt()}
    if p_sum is not None and ent_sum is not None:
        probs = p_sum / samples
        entropy = _entropy(probs, dim=1)
        result["classes"] = {
            "probs": probs,
            "entropy": entropy,
            "mutual_info": (entropy - ent_sum / samples).clamp_min(0),
        }
    return result


__all__ = ["mc_dropout_mode", "mc_predict"]
