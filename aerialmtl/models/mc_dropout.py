"""Monte-Carlo dropout (Gal & Ghahramani 2016): T stochastic decoder passes → mean and spread.

Only the dropout layers are stochastic at test time; BatchNorm stays in eval mode (running statistics
used and never updated). Because every dropout layer of :class:`~aerialmtl.models.d3net.D3Net` sits in
``decode``, :func:`mc_predict` runs the encoder ONCE and repeats its features along the batch to
sample the decoder, ``sample_batch`` samples at a time.

Outputs per enabled task:

* ``height``: ``mean`` and ``std`` (B×1×H×W, metres; std is the population std over the T samples,
  the epistemic spread).
* ``shadow`` (a model with the shadow head, ``cfg.shadow_head``): ``shadow_head`` (B×H×W), the mean over the
  samples of the sigmoid of its logit, P(cast shadow) in [0, 1].
* ``classes``: ``probs`` (B×K×H×W, mean softmax), ``entropy`` (B×H×W, nats, predictive entropy
  H[mean p] ∈ [0, log K]) and ``mutual_info`` (B×H×W, nats, H[mean p] − mean_t H[p_t], clamped ≥ 0;
  the BALD epistemic part).

All statistics are accumulated in float32 (also under bf16 autocast); the height spread uses Chan's
parallel combination of per-chunk means and squared deviations (Welford), which stays stable for
heights far from zero.

:func:`mc_statistics` returns the raw statistics a stitcher blends (:class:`McStatistics`: mean
height, height std, mean probabilities channels-last, mean per-sample entropy); :func:`mc_predict`
derives the entropy of the mean and the mutual information from them. On a CPU the per-sample class
statistics run in one pass over the logits (:mod:`aerialmtl.models.class_kernel`, a numba kernel: 2–3×
faster than the torch operations at K = 20, the same numbers to 1e-6). Elsewhere they are computed with torch
row block by row block (4 MiB temporaries), each block gathered from the model's channels-last logits
into K class planes so that the max and the sums over classes vectorise over pixels; the mean
probabilities return to channels last once per window. The per-sample entropy costs one logarithm per
pixel instead of K: with
``d = z − max_k z`` and ``S = Σ_k exp(d_k)``, ``p = exp(d) / S`` and ``H_t = log S − Σ_k exp(d_k)·d_k / S``
(= logsumexp(z) − Σ softmax(z)·z).

Dropout masks. By default they come from torch's global RNG, so they depend on how windows are batched
and samples chunked. With ``keys`` (one integer per image of the batch, e.g. a window index), the mask
of image ``b`` in sample ``t`` is drawn from a generator seeded by ``(seed, keys[b], t)``: results no
longer depend on the batch, the sample chunks or which process computes the window (``nn.Dropout`` and
``nn.Dropout1d/2d/3d``; alpha-dropout layers keep the global RNG).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import nn

from aerialmtl.models import class_kernel
from aerialmtl.models.config import HEIGHT_SCALE, SHADOW
from aerialmtl.models.d3net import decode_features, encode_features
from aerialmtl.models.familiarity import FeatureDensity

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


#: Dropout modules whose masks :func:`mc_statistics` can draw per image from seeded generators.
_SEEDABLE = (nn.Dropout, nn.Dropout1d, nn.Dropout2d, nn.Dropout3d)


def _dropout_p(module: nn.Module) -> float:
    """The drop probability of a seedable dropout layer (the forward hooks here are registered on those only)."""
    assert isinstance(module, _SEEDABLE), f"a dropout hook on {type(module).__name__}"
    return float(module.p)
#: Elements per temporary of the softmax/entropy loop (4 MiB of float32; 1 MiB and 16 MiB were slower).
_ROW_BLOCK_ELEMENTS = 1 << 20


def sample_seed(seed: int, key: int, sample: int) -> int:
    """The 63-bit seed of the dropout masks of image ``key`` in MC sample ``sample``."""
    state = np.random.SeedSequence([int(seed) & (2**63 - 1), int(key) & (2**63 - 1), int(sample)])
    return int(state.generate_state(1, np.uint64)[0]) & (2**63 - 1)


class _SeededMasks:
    """Forward hooks that apply per-image seeded dropout masks (dropout modules otherwise in eval mode).

    ``generators`` holds one generator per image of the batch the next ``decode`` call sees, in batch
    order; each hook draws the masks of image ``n`` from ``generators[n]``, so an image's masks depend
    only on its generator, never on the other images of the batch.
    """

    def __init__(self, model: nn.Module) -> None:
        self.model = model
        self.generators: list[torch.Generator] = []
        self._handles: list[torch.utils.hooks.RemovableHandle] = []

    def _hook(self, module: nn.Module, inputs: tuple[torch.Tensor, ...], output: torch.Tensor) -> torch.Tensor:
        p = _dropout_p(module)
        if p <= 0.0:
            return output
        x = output  # eval mode: the module returned its input unchanged
        if x.shape[0] != len(self.generators):  # pragma: no cover - guarded by mc_statistics
            raise RuntimeError(f"seeded dropout: batch of {x.shape[0]} images but {len(self.generators)} generators")
        keep = 1.0 - p
        if isinstance(module, nn.Dropout):
            shape = tuple(x.shape[1:])
        else:  # channel-wise dropout: one draw per channel
            shape = (x.shape[1],) + (1,) * (x.dim() - 2)
        mask = torch.empty((x.shape[0], *shape), dtype=torch.float32, device=x.device)
        for n, gen in enumerate(self.generators):
            mask[n].bernoulli_(keep, generator=gen)
        mask.div_(keep)
        return x * mask.to(x.dtype)

    def __enter__(self) -> _SeededMasks:
        for m in self.model.modules():
            if isinstance(m, _SEEDABLE):
                m.eval()
                self._handles.append(m.register_forward_hook(self._hook))
        return self

    def __exit__(self, *exc: object) -> None:
        for h in self._handles:
            h.remove()
        self._handles.clear()


@contextlib.contextmanager
def _seeded_mode(model: nn.Module, masks: _SeededMasks) -> Iterator[nn.Module]:
    """Eval mode with seeded masks on the seedable dropout layers (alpha dropout: global RNG); modes restored."""
    modes = {m: m.training for m in model.modules()}
    try:
        model.eval()
        for m in model.modules():
            if isinstance(m, (nn.AlphaDropout, nn.FeatureAlphaDropout)):
                m.train()
        with masks:
            yield model
    finally:
        for m, mode in modes.items():
            m.training = mode


@dataclass
class McStatistics:
    """What T MC-dropout samples say about each pixel (float32, on the input's device).

    Attributes:
        height_mean, height_std: B×H×W metres; ``None`` without height. ``height_std`` is the predictive
            standard deviation: the population std of the T sampled heights (epistemic) and, for a model
            with an aleatoric height head, the Laplace part too: ``sqrt(var_t μ_t + mean_t 2·b_t²)``
            (:func:`predictive_std`).
        height_aleatoric: B×H×W ``sqrt(mean_t 2·b_t²)`` (metres), the aleatoric part alone; ``None`` for a
            model without an aleatoric head.
        probs: B×H×W×K mean class probabilities (channels last); ``None`` without classes.
        mean_entropy: B×H×W mean over the samples of each sample's entropy (nats), i.e. the expected
            entropy; the mutual information is ``H[probs] − mean_entropy``.
        unfamiliarity: B×H×W in [0, 1], from the encoder's features and the checkpoint's feature density
            (:meth:`FeatureDensity.unfamiliarity <aerialmtl.models.familiarity.FeatureDensity.unfamiliarity>`);
            ``None`` without a density.
        shadow, shadow_on, shadow_height, shadow_weight: B×H×W, set after the model by the shadow features
            (:mod:`aerialmtl.inference.shadows`): the probability of cast shadow where the sun is known
            (``shadow_on`` 1 there, else 0), the shadow-measured height times ``shadow_weight`` (1 where measured,
            else 0); ``None`` without the feature.
    """

    height_mean: torch.Tensor | None = None
    height_std: torch.Tensor | None = None
    probs: torch.Tensor | None = None
    mean_entropy: torch.Tensor | None = None
    height_aleatoric: torch.Tensor | None = None
    unfamiliarity: torch.Tensor | None = None
    shadow: torch.Tensor | None = None
    shadow_on: torch.Tensor | None = None
    shadow_height: torch.Tensor | None = None
    shadow_weight: torch.Tensor | None = None
    shadow_head: torch.Tensor | None = None

    def map(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> McStatistics:
        """A copy with ``fn`` applied to every statistic present (e.g. one window of a batch, a view undone)."""
        return McStatistics(**{f.name: None if getattr(self, f.name) is None else fn(getattr(self, f.name))
                               for f in fields(self)})


def class_probabilities(logits: torch.Tensor) -> torch.Tensor:
    """B×K×H×W logits → B×H×W×K float32 softmax (the per-pixel kernel over the last dimension).

    Each pixel's probabilities are computed alone, so they do not depend on the batch or the
    position of the window (unlike a softmax over dimension 1, whose rounding follows the memory layout).
    """
    zl = logits.float().permute(0, 2, 3, 1)
    return torch.softmax(zl if zl.is_contiguous() else zl.contiguous(), dim=-1)


def _class_sums(logits: torch.Tensor, s: int, b: int, p_sum: torch.Tensor | None = None,
                e_sum: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The class sums over ``s`` MC samples of (s·B)×K×H×W logits.

    Sample-major: sample ``t`` of image ``n`` at ``t·B + n``. The sums over these ``s`` samples: Σ_t p_t
    (K×B×H×W class planes) and Σ_t H_t (B×H×W, nats), float32; added into ``p_sum`` and ``e_sum`` when given,
    else new. On a CPU by :mod:`aerialmtl.models.class_kernel` (one pass per sample),
    elsewhere (or without numba) by :func:`_class_sums_torch`; the two agree to 1e-6.
    """
    if logits.device.type == "cpu" and class_kernel.available():
        if p_sum is None or e_sum is None:
            k, h, w = logits.shape[1:]
            p_sum = torch.zeros((k, b, h, w), dtype=torch.float32)
            e_sum = torch.zeros((b, h, w), dtype=torch.float32)
        z = logits.float()
        nhwc = z.permute(0, 2, 3, 1)
        if nhwc.is_contiguous() and not z.is_contiguous():  # channels last (OpenVINO's decoder, torch's model)
            class_kernel.add_class_sums(nhwc.numpy(), b, p_sum.numpy(), e_sum.numpy(), channels_last=True)
        else:
            class_kernel.add_class_sums(z.contiguous().numpy(), b, p_sum.numpy(), e_sum.numpy())
        return p_sum, e_sum
    return _class_sums_torch(logits, s, b, p_sum, e_sum)


def _class_sums_torch(logits: torch.Tensor, s: int, b: int, p_sum: torch.Tensor | None = None,
                      e_sum: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_class_sums` with torch operations (any device), row block by row block.

    Σ_t p_t (K×B×H×W class
    planes) and Σ_t H_t (B×H×W, nats), float32; added into ``p_sum`` and ``e_sum`` when given (the sums of
    earlier samples: ``p_sum + Σ_t p_t``), else new.

    Each block is gathered into class planes (K×N×rows×W) first: the max and the sums over K are then
    reductions across K whole planes, which vectorise over pixels, where reductions over K = 20 adjacent
    values of a channels-last tensor do not (1.4–2× faster for the whole function on 2 Zen 4 cores,
    bench/RESULTS.md). A block's sum over the samples is formed in a block-sized scratch and added into the
    running sums there, so no chunk-sized array is made per call: a fresh 80 MiB array per chunk (1024²,
    K = 20) cost its page faults every time (31 % of the function's time in a torch.profiler run; the sums are
    the same, in the same order).
    """
    n, k, h, w = logits.shape
    zp = logits.permute(1, 0, 2, 3)  # K×N×H×W (a view)
    fresh = p_sum is None or e_sum is None
    if p_sum is None or e_sum is None:
        p_sum = torch.empty((k, b, h, w), dtype=torch.float32, device=logits.device)
        e_sum = torch.empty((b, h, w), dtype=torch.float32, device=logits.device)
    rows = max(1, _ROW_BLOCK_ELEMENTS // max(1, n * w * k)) if logits.device.type == "cpu" else h
    p_scratch = e_scratch = None
    if s > 1 and not fresh:
        p_scratch = torch.empty((k, b, min(rows, h), w), dtype=torch.float32, device=logits.device)
        e_scratch = torch.empty((b, min(rows, h), w), dtype=torch.float32, device=logits.device)
    for r in range(0, h, rows):
        z = zp[:, :, r:r + rows].float().contiguous()  # K×N×rows×W planes
        d = z.sub_(z.amax(0))  # ≤ 0, exactly 0 at the largest logit
        e = torch.exp(d)
        inv = e.sum(0).reciprocal_()  # 1 / S
        ent = d.mul_(e).sum(0).mul_(inv).neg_().sub_(torch.log(inv))  # log S − Σ e·d / S
        ent.clamp_min_(0.0)
        e.mul_(inv)
        m = e.shape[2]
        p_rows, e_rows = p_sum[:, :, r:r + m], e_sum[:, r:r + m]
        if fresh:  # the sums of these samples are the running sums
            _sum_samples(e, p_rows, 1, s, b)
            _sum_samples(ent, e_rows, 0, s, b)
        elif p_scratch is None or e_scratch is None:  # one sample: added as it is
            p_rows.add_(e)
            e_rows.add_(ent)
        else:
            p_chunk, e_chunk = p_scratch[:, :, :m], e_scratch[:, :m]
            _sum_samples(e, p_chunk, 1, s, b)
            _sum_samples(ent, e_chunk, 0, s, b)
            p_rows.add_(p_chunk)
            e_rows.add_(e_chunk)
    return p_sum, e_sum


def _sum_samples(x: torch.Tensor, out: torch.Tensor, dim: int, s: int, b: int) -> None:
    """``out = Σ_t x[..., t·b:(t+1)·b, ...]`` along ``dim``, as s − 1 element-wise adds into ``out``.

    For a
    chunk of 2 samples of 1024², K = 20, :func:`_class_sums` took 0.34 s instead of 0.47 s with
    ``x.unflatten(dim, (s, b)).sum(dim)`` copied into ``out`` (1 thread, Zen 4, load ~10; the same sums).
    """
    if s == 1:
        out.copy_(x.narrow(dim, 0, b))
        return
    torch.add(x.narrow(dim, 0, b), x.narrow(dim, b, b), out=out)
    for t in range(2, s):
        out.add_(x.narrow(dim, t * b, b))


@torch.no_grad()
def mc_statistics(
    model: nn.Module,
    x: torch.Tensor,
    samples: int,
    sample_batch: int | None = None,
    seed: int | None = None,
    keys: Sequence[int] | None = None,
    density: FeatureDensity | None = None,
    tasks: Collection[str] | None = None,
) -> McStatistics:
    """MC-dropout statistics of a D3-Net-like model (with ``encode``/``decode``); encoder run once.

    Args:
        model: a model with ``encode(x) -> list[Tensor]`` (deterministic) and ``decode(feats) -> dict``.
        x: B×C×H×W normalised image batch.
        samples: T ≥ 1 decoder samples.
        sample_batch: decode at most this many samples per pass (bounds memory: the decoder sees
            ``B·sample_batch`` images at once); default all T at once.
        seed: without ``keys``: seed torch's global RNG for the masks (its state is restored afterwards);
            with ``keys``: the base seed of the per-image generators (default 0).
        keys: one integer per image; image ``b``'s masks in sample ``t`` come from a generator seeded by
            ``(seed, keys[b], t)`` (see the module docstring).
        density: the checkpoint's feature density: ``unfamiliarity`` from the encoder's features too.
        tasks: decode only these tasks (a D3-Net's; default all): the same statistics of them, the others'
            decoder blocks not run.

    Returns:
        :class:`McStatistics` for the tasks the model returns.
    """
    if samples < 1:
        raise ValueError(f"mc_predict: samples must be ≥ 1, got {samples}")
    b = x.shape[0]
    if keys is not None and len(keys) != b:
        raise ValueError(f"mc_statistics: {len(keys)} keys for a batch of {b} images")
    chunk = samples if sample_batch is None else max(1, min(int(sample_batch), samples))
    masks = _SeededMasks(model) if keys is not None else None
    if masks is not None:
        mode: contextlib.AbstractContextManager[object] = _seeded_mode(model, masks)
        rng: contextlib.AbstractContextManager[object] = contextlib.nullcontext()
    else:
        mode = mc_dropout_mode(model)
        devices = [x.device] if x.device.type == "cuda" else []
        rng = torch.random.fork_rng(devices=devices) if seed is not None else contextlib.nullcontext()
    with mode, rng:
        if masks is None and seed is not None:
            torch.manual_seed(seed)
        feats = encode_features(model, x)

        def decode_chunk(done: int, s: int) -> dict[str, torch.Tensor]:
            if masks is not None:
                assert keys is not None
                masks.generators = [sample_generator(seed or 0, key, t, x.device)
                                    for t in range(done, done + s) for key in keys]
            return decode_features(model, [f.repeat(s, 1, 1, 1) if s > 1 else f for f in feats], tasks)

        stats = accumulate_samples(decode_chunk, samples, chunk, b)
    if density is not None:
        stats.unfamiliarity = density.unfamiliarity(feats, (x.shape[-2], x.shape[-1]))
    return stats


def sample_generator(seed: int, key: int, sample: int, device: torch.device | str = "cpu") -> torch.Generator:
    """The generator of the dropout masks of image ``key`` in MC sample ``sample`` (:func:`sample_seed`)."""
    gen = torch.Generator(device=device)
    gen.manual_seed(sample_seed(seed, key, sample))
    return gen


def accumulate_samples(decode_chunk: Callable[[int, int], dict[str, torch.Tensor]], samples: int, chunk: int,
                       b: int) -> McStatistics:
    """The MC statistics of ``samples`` decoder samples of ``b`` images, decoded ``chunk`` samples at a time.

    The one accumulation of every engine (torch here, OpenVINO in :mod:`aerialmtl.inference.engines`).

    Args:
        decode_chunk: ``(done, s)`` → the decoder outputs of samples ``done … done + s − 1`` of the ``b``
            images, sample-major along the batch (``(s·b)×C×H×W``; index ``t·b + n``).
        samples: T.
        chunk: samples per call.
        b: images.
    """
    stats = McStatistics()
    h_mean: torch.Tensor | None = None
    h_m2: torch.Tensor | None = None
    p_sum: torch.Tensor | None = None
    ent_sum: torch.Tensor | None = None
    a_sum: torch.Tensor | None = None
    s_sum: torch.Tensor | None = None
    done = 0
    while done < samples:
        s = min(chunk, samples - done)
        out = decode_chunk(done, s)
        if "height" in out:
            hs = out["height"].float().unflatten(0, (s, b))[:, :, 0]  # s×B×H×W
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
        if HEIGHT_SCALE in out:
            c_a = laplace_variance(out[HEIGHT_SCALE]).unflatten(0, (s, b))[:, :, 0].sum(0)
            a_sum = c_a if a_sum is None else a_sum.add_(c_a)
        if SHADOW in out:
            c_s = torch.sigmoid(out[SHADOW].float()).unflatten(0, (s, b))[:, :, 0].sum(0)
            s_sum = c_s if s_sum is None else s_sum.add_(c_s)
        if "classes" in out:  # added into the running sums (no chunk-sized array per call)
            p_sum, ent_sum = _class_sums(out["classes"], s, b, p_sum, ent_sum)
        done += s
    if h_mean is not None and h_m2 is not None:
        stats.height_mean = h_mean
        epistemic_var = (h_m2 / samples).clamp_min(0)
        if a_sum is not None:
            aleatoric_var = a_sum.div_(samples)
            stats.height_aleatoric = aleatoric_var.sqrt()
            stats.height_std = predictive_std(epistemic_var, aleatoric_var)
        else:
            stats.height_std = epistemic_var.sqrt()
    if s_sum is not None:
        stats.shadow_head = s_sum.div_(samples)
    if p_sum is not None and ent_sum is not None:
        stats.probs = p_sum.div_(samples).permute(1, 2, 3, 0).contiguous()  # planes → channels last, once
        stats.mean_entropy = ent_sum.div_(samples)
    return stats


def laplace_variance(scale: torch.Tensor) -> torch.Tensor:
    """Variance ``2·b²`` (m²) of a Laplace distribution of scale ``b`` (metres), float32."""
    b = scale.float()
    return 2.0 * b * b


def predictive_std(epistemic_var: torch.Tensor, aleatoric_var: torch.Tensor) -> torch.Tensor:
    """The predictive standard deviation (metres) of a mixture of T Laplace samples, from its two parts (m²).

    ``sqrt(var_t μ_t + mean_t 2·b_t²)`` (the law of total variance; Kendall & Gal 2017).
    """
    return (epistemic_var + aleatoric_var).clamp_min(0).sqrt()


def single_pass_statistics(raw: dict[str, torch.Tensor]) -> McStatistics:
    """The statistics of one deterministic pass (T = 1) from the model's outputs (any engine).

    ``height_std`` is the aleatoric spread ``sqrt(2)·b`` for a model with an aleatoric head, ``None`` otherwise.
    """
    stats = McStatistics()
    if "height" in raw:
        stats.height_mean = raw["height"][:, 0].float()
    if HEIGHT_SCALE in raw:
        stats.height_aleatoric = laplace_variance(raw[HEIGHT_SCALE][:, 0]).sqrt()
        stats.height_std = stats.height_aleatoric
    if "classes" in raw:
        stats.probs = class_probabilities(raw["classes"])
    if SHADOW in raw:
        stats.shadow_head = torch.sigmoid(raw[SHADOW][:, 0].float())
    return stats


@dataclass(frozen=True)
class DropoutSite:
    """One seedable dropout layer of a decoder, in the order the decoder calls it.

    Attributes:
        p: its dropout probability.
        channels: channels of its input.
        stride: its resolution relative to the image (its input is ``channels × H/stride × W/stride``).
        channelwise: one draw per channel (``Dropout1d/2d/3d``) instead of one per element.
    """

    p: float
    channels: int
    stride: int
    channelwise: bool = False

    def shape(self, height: int, width: int) -> tuple[int, ...]:
        """The mask shape of one image of ``height × width`` pixels."""
        if self.channelwise:
            return (self.channels, 1, 1)
        return (self.channels, height // self.stride, width // self.stride)


@torch.no_grad()
def dropout_sites(model: nn.Module, in_channels: int, probe: int = 64) -> list[DropoutSite]:
    """The seedable dropout layers (``p > 0``) of ``model.decode``, in call order.

    Found by one small probe pass (``probe × probe`` zeros).
    """
    sites: list[DropoutSite] = []
    handles = []

    def hook(module: nn.Module, inputs: tuple[torch.Tensor, ...], output: torch.Tensor) -> None:
        p = _dropout_p(module)
        if p > 0:
            x = inputs[0]
            sites.append(DropoutSite(p, int(x.shape[1]), probe // int(x.shape[-1]), not isinstance(module, nn.Dropout)))

    for m in model.modules():
        if isinstance(m, _SEEDABLE):
            handles.append(m.register_forward_hook(hook))
    modes = {m: m.training for m in model.modules()}
    try:
        model.eval()
        param = next(model.parameters(), None)
        device = param.device if param is not None else torch.device("cpu")
        x = torch.zeros((1, in_channels, probe, probe), device=device)
        decode_features(model, encode_features(model, x))
    finally:
        for h in handles:
            h.remove()
        for m, mode in modes.items():
            m.training = mode
    return sites


def dropout_masks(sites: Sequence[DropoutSite], height: int, width: int, seed: int, key: int,
                  sample: int) -> list[torch.Tensor]:
    """The dropout masks of image ``key`` in MC sample ``sample``, one per site.

    Each 1×C×h×w float32, values 0 or 1/(1 − p).

    Drawn from the same generator, in the same order, with the same calls as the seeded hooks of
    :func:`mc_statistics`, so an engine that multiplies its dropout inputs by them gives the samples of
    the torch path.
    """
    gen = sample_generator(seed, key, sample)
    out = []
    for site in sites:
        keep = 1.0 - site.p
        mask = torch.empty(site.shape(height, width), dtype=torch.float32).bernoulli_(keep, generator=gen)
        out.append(mask.div_(keep).unsqueeze(0))
    return out


@torch.no_grad()
def mc_predict(
    model: nn.Module,
    x: torch.Tensor,
    samples: int,
    sample_batch: int | None = None,
    seed: int | None = None,
    keys: Sequence[int] | None = None,
    tasks: Collection[str] | None = None,
) -> dict[str, dict[str, torch.Tensor]]:
    """MC-dropout prediction of a D3-Net-like model (with ``encode``/``decode``).

    Args:
        model: a model with ``encode(x) -> list[Tensor]`` (deterministic) and ``decode(feats) -> dict``.
        x: B×C×H×W normalised image batch.
        samples: T ≥ 1 decoder samples (T = 1 gives std 0 and mutual information 0).
        sample_batch: decode at most this many samples per pass (bounds memory: the decoder sees
            ``B·sample_batch`` images at once); default all T at once.
        seed: seed the dropout masks (the global RNG state is restored afterwards); default: the
            current global RNG. With ``keys``, the base seed of the per-image masks.
        keys: per-image mask seeds (see :func:`mc_statistics`).
        tasks: only these tasks (see :func:`mc_statistics`).

    Returns:
        ``{"height": {"mean", "std"}, "classes": {"probs", "entropy", "mutual_info"}}`` for the tasks the
        model returns, float32 (shapes in the module docstring).
    """
    stats = mc_statistics(model, x, samples, sample_batch, seed, keys, tasks=tasks)
    result: dict[str, dict[str, torch.Tensor]] = {}
    if stats.height_mean is not None and stats.height_std is not None:
        result["height"] = {"mean": stats.height_mean.unsqueeze(1), "std": stats.height_std.unsqueeze(1)}
        if stats.height_aleatoric is not None:
            result["height"]["aleatoric_std"] = stats.height_aleatoric.unsqueeze(1)
    if stats.probs is not None and stats.mean_entropy is not None:
        entropy = _entropy(stats.probs, dim=-1)
        # one sample has no epistemic part; the two entropy formulas differ in the last bit
        mi = (entropy - stats.mean_entropy).clamp_min(0) if samples > 1 else torch.zeros_like(entropy)
        result["classes"] = {"probs": stats.probs.permute(0, 3, 1, 2), "entropy": entropy, "mutual_info": mi}
    return result


__all__ = ["DropoutSite", "McStatistics", "accumulate_samples", "laplace_variance", "predictive_std",
           "single_pass_statistics", "class_probabilities", "dropout_masks", "dropout_sites",
           "mc_dropout_mode", "mc_predict", "mc_statistics", "sample_generator", "sample_seed"]
