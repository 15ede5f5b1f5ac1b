"""Heights from the sun inside predict: per window, the shadow layer, heights chosen by rendering shadows, and
(with ``shadow_fusion``) those heights fused into the network's own objects.

For each window the model has computed (its statistics still per window, before blending,
:mod:`aerialmtl.inference.stitch`):

1. ``shadow`` — the probability that each pixel is a cast shadow, from its colour and its neighbourhood, by the
   shadow classifier fitted on the training area at its sun (:class:`aerialmtl.sun.ShadowModel`, stored in the
   checkpoint's ``meta.sun``): learnt there from the training heights' cast shadows, so the area's water and
   dark roofs are not shadows; where the network has a shadow head (``model.shadow_head``), its P(cast shadow)
   instead (``McStatistics.shadow_head``, the mean over the MC samples; threshold :data:`HEAD_THRESHOLD`);
2. ``shadow_height`` — per object the network finds (connected pixels predicted ≥ :data:`OBJECT_MIN_M`), the
   height whose rendered cast shadow — the whole window's, so occluders and shadows falling on other objects
   count — best matches the shadow probability (:func:`aerialmtl.sun.rendered_heights`), painted over the
   object; nodata where the match curve is flat (the shadow hidden, or cut by the window's edge — the
   neighbouring window, which overlaps, may measure it);
3. with ``shadow_fusion``, the height and its spread of each measured object move towards the rendered height by
   inverse-variance weighting (:func:`aerialmtl.sun.fuse_rendered`): never outside an object (flat ground is
   never raised; pixels the rendering took as the object's spill into its own shadow can only be lowered), and
   the disagreement of the two widens the spread.

The statistics leave here as they came where the sun is off (``--sun none`` or no sun for the input): the
maps are then those of a run without the feature, to the bit.

Pixels that are not data (nodata, NaN, outside the AOI) are nodata in both layers, and take no part in any other
pixel's probability (the classifier's neighbourhoods leave them out, :meth:`aerialmtl.sun.ShadowModel.predict_proba`).
Where a window's probability cannot be made (a window of one colour: all black, a constant fill; colours the
classifier cannot read), its layers are nodata, never 0 ("no shadow") nor 1, and the input gets one warning. The
layers are made from a probability and the mask of the pixels where it is one (:func:`window_layers`), whatever
gives the probability.
"""

from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
import torch
from scipy import ndimage

from aerialmtl.models.mc_dropout import McStatistics
from aerialmtl.sun import RenderSettings, ShadowModel, Sun, fuse_rendered, rendered_heights
from aerialmtl.sun.colour import unit_rgb

#: Pixels the network predicts at least this high (metres) form its objects.
OBJECT_MIN_M = 2.0
#: A window whose valid pixels' colours all lie within this span (unit RGB, every band: one 8-bit level) has no
#: contrast to find a shadow in (all black, a constant fill): its shadow layers are nodata.
MIN_CONTRAST = 1.0 / 255.0
#: Suns taken on trust, checked on the orthophoto itself: the training fit (same flight by place alone) and a
#: TIFF ``DateTime`` (often when the file was written). ``--sun``, ``--acquired`` and a STAC time always win.
CHECKED_SOURCES = ("training fit", "TIFF DateTime")
#: A sun whose azimuth lies further than this (degrees) from the one the orthophoto's own shadows give, and which
#: explains them less than :data:`CHECK_RATIO` as well, is wrong for it: the shadow layers are switched off for that
#: orthophoto, with a warning giving both.
CHECK_AZIMUTH_DEG = 10.0
#: The share of the best sun's correlation below which the chosen sun is refuted. With the network's heights the
#: correlation is flat in azimuth: on autzen_west's validation and held-out blocks the training fit (the same
#: flight) scored 0.80–0.98 of the best sun's, a sun 14° wrong on a synthetic city 0.91–0.96, 30° wrong 0.73–0.74,
#: 50–80° wrong 0.56–0.66. So only a sun far from the image's (another time of day) is refuted; see
#: experiments/heights_from_the_sun/README.md.
CHECK_RATIO = 0.7
#: Pixels predicted ≥ :data:`OBJECT_MIN_M` (and as many on the ground) a window needs to check the sun.
CHECK_MIN_PX = 1500
#: Objects (of at least :attr:`aerialmtl.sun.RenderSettings.min_object_m2`) a window needs to check the sun: each
#: shows the direction its shadow falls once. A 64 m synthetic town whose network merged its houses into 5 blobs
#: spilling over their own shadows scored the opposite direction best (314° for a sun at 136°, r = 0.17): a
#: refutation needs more objects than that.
CHECK_MIN_OBJECTS = 10
#: Windows with enough objects whose fit is unclear before the sun is taken as it is (each ~1 s on a 1056² window).
CHECK_TRIES = 3
#: Least correlation of the target's best sun (:func:`aerialmtl.sun.fit.check_azimuth`) for its azimuth to be trusted.
CHECK_MIN_SCORE = 0.15

#: The shadow head's P(cast shadow) above which a pixel is shadow for the runs (a calibrated probability's half).
HEAD_THRESHOLD = 0.5


def unit_colours(data: np.ndarray, rescale: tuple[float, float] | None, train_dtype: str | None) -> np.ndarray:
    """float32 (3, h, w) colours of a window's raw values ``data`` (3, h, w) as the shadow classifier was fitted
    on them: the values the model trained on (``rescale`` = ``--rescale-input``'s ``(a, b)``: ``a·x + b``) on the
    scale of the training data's type ``train_dtype`` (:func:`aerialmtl.sun.colour.unit_rgb`, as it scaled the
    training patches), whatever this orthophoto's own type: a uint16 orthophoto holding 8-bit values is read as
    8-bit values, not as 1/257 of them.
    """
    x = data.astype(np.float32)
    if rescale is not None:
        x = x * np.float32(rescale[0]) + np.float32(rescale[1])
    return unit_rgb(x, train_dtype or "uint8")


class Probability(NamedTuple):
    """A window's shadow probability, whatever computes it.

    Attributes:
        prob: float32 (h, w), 0–1 where :attr:`made`, NaN elsewhere.
        made: bool (h, w): the pixels whose probability is data (valid input the source could read).
        why: why valid pixels have none (one phrase for the warning), ``None`` when every valid pixel has one.
    """

    prob: np.ndarray
    made: np.ndarray
    why: str | None = None


class _Window(NamedTuple):
    """One window's layers, (h, w) each: shadow probability (0 where not made), where it is data, measured shadow
    height in metres (0 where none), where one was measured, the fused (height, spread) or ``None``, and why valid
    pixels have no probability (``None``: none lack one).
    """

    shadow: np.ndarray
    made: np.ndarray
    height: np.ndarray
    measured: np.ndarray
    fused: tuple[np.ndarray, np.ndarray] | None
    why: str | None = None


def colour_probability(model: ShadowModel, rgb: np.ndarray, ok: np.ndarray, gsd_m: float,
                       workers: int = 1) -> Probability:
    """The colour classifier's :class:`Probability` of a window: ``rgb`` (3, h, w) colours (:func:`unit_colours`),
    ``ok`` bool (h, w) the valid input pixels, ``gsd_m`` metres; ``workers`` threads.

    None where ``ok`` is False or the colour is unreadable (NaN, negative); none at all in a window without
    contrast (every valid colour within :data:`MIN_CONTRAST`: a black or constant fill casts no shadow to see).
    """
    made = ok & np.isfinite(rgb).all(0)
    nothing = np.full(ok.shape, np.nan, np.float32)
    if not made.any():
        return Probability(nothing, made, "colours that are not finite numbers" if ok.any() else None)
    hi = np.where(made, rgb, np.float32(-np.inf)).max(axis=(1, 2))
    lo = np.where(made, rgb, np.float32(np.inf)).min(axis=(1, 2))
    if float((hi - lo).max()) < MIN_CONTRAST:
        return Probability(nothing, np.zeros_like(ok), "no contrast (one colour: all black or a constant fill)")
    prob = model.predict_proba(rgb, gsd_m, workers, valid=ok)
    made = ok & np.isfinite(prob)
    why = "colours the shadow classifier cannot read (negative or not finite)" if (ok & ~made).any() else None
    return Probability(np.where(made, prob, np.float32(np.nan)).astype(np.float32), made, why)


def head_probability(head: np.ndarray, ok: np.ndarray) -> Probability:
    """The shadow head's :class:`Probability` of a window: its P(cast shadow) ``head`` float32 (h, w) (the mean over
    the MC samples, ``McStatistics.shadow_head``) where ``ok`` (bool (h, w), the valid input) and it is finite.
    """
    made = ok & np.isfinite(head)
    return Probability(np.where(made, head, np.float32(np.nan)).astype(np.float32), made, None)


def window_layers(p: Probability, height: np.ndarray, spread: np.ndarray | None, sun: Sun, gsd_m: float,
                  threshold: float, fuse: bool) -> _Window:
    """The layers of one window from its shadow probability ``p`` (any source): ``height``/``spread`` float32
    (h, w) metres (the network's), ``sun`` on the window's grid, ``gsd_m`` metres, the probability ``threshold``
    from which an object's pixel is a candidate for its spill; the fused height and spread only with ``fuse``, a
    spread and a measure.

    Objects are found, and their rendered shadows compared, where the probability is data only: a pixel without
    one is nodata in both layers, never "no shadow", and no evidence either way.
    """
    if not p.made.any():
        return _Window(np.zeros(height.shape, np.float32), p.made, np.zeros(height.shape, np.float32),
                       np.zeros(height.shape, bool), None, p.why)
    objects, _ = ndimage.label((height >= OBJECT_MIN_M) & p.made)
    # the probability as it is; the decision threshold (chosen on the training area) marks spill candidates
    measured = rendered_heights(p.prob, gsd_m, sun, objects, np.where(p.made, height, np.float32(np.nan)),
                                RenderSettings(threshold=threshold))
    has = np.isfinite(measured.height) & p.made
    fused = None
    if fuse and spread is not None and (has.any() or measured.spill.any()):
        fused = fuse_rendered(height, spread, measured)
    return _Window(np.where(p.made, p.prob, np.float32(0.0)).astype(np.float32), p.made,
                   np.where(has, measured.height, 0.0).astype(np.float32), has, fused, p.why)


class ShadowStep:
    """The shadow layers (and fusion) of one window batch; see the module docstring.

    Args:
        model: the training area's shadow classifier.
        gsd_m: the prediction grid's pixel size, metres.
        fuse: fuse the shadow heights into the height map and its spread.
        workers: threads of the step (the run's inference threads: the model waits meanwhile at T > 1, and
            scipy's filters and numpy release the GIL): a batch's windows at once, or a lone window's shadow
            classifier (its filters and bands of rows); the layers do not depend on it.
    """

    def __init__(self, model: ShadowModel, gsd_m: float, fuse: bool, workers: int = 1) -> None:
        self.model, self.gsd_m, self.fuse = model, float(gsd_m), bool(fuse)
        self.workers = max(1, int(workers))
        self._warned: set[tuple[str, str]] = set()
        #: per input checked on its own shadows: ``None`` (the sun holds) or why the layers are off for it
        self.checked: dict[str, str | None] = {}
        self._tries: dict[str, int] = {}

    def check_sun(self, key: str, sun: Sun, source: str, stats: McStatistics, rgb: list[np.ndarray],
                  valid: torch.Tensor) -> str | None:
        """Check a sun taken on trust (:data:`CHECKED_SOURCES`) on the orthophoto ``key``'s own shadows, once.

        On the first window with enough objects and ground (:data:`CHECK_MIN_PX` each, and
        :data:`CHECK_MIN_OBJECTS` objects), the azimuth whose cast
        shadows of the predicted heights best match the image's shadow score (:func:`aerialmtl.sun.fit.check_azimuth`,
        a clear fit) is where the shadows fall; no elevation is fitted (the network's heights scale it). The sun
        is refuted when it lies more than :data:`CHECK_AZIMUTH_DEG` away and explains the shadows less than
        :data:`CHECK_RATIO` as well at any elevation searched. Windows too empty to tell leave the check for the
        next batch; after :data:`CHECK_TRIES` unclear ones the sun holds.

        Returns:
            ``None`` while the sun holds (or cannot be checked yet), else one line saying why it is off for this
            orthophoto (the caller switches the layers off and records it).
        """
        if key in self.checked:
            return self.checked[key]
        if source not in CHECKED_SOURCES or stats.height_mean is None:
            self.checked[key] = None
            return None
        from aerialmtl.sun.fit import check_azimuth

        heights = stats.height_mean.detach().float().cpu().numpy()
        ok_all = valid.cpu().numpy()
        for n in range(min(len(rgb), heights.shape[0])):
            ok = ok_all[n] & np.isfinite(heights[n])
            tall = int((ok & (heights[n] >= OBJECT_MIN_M)).sum())
            if tall < CHECK_MIN_PX or int(ok.sum()) - tall < CHECK_MIN_PX:
                continue
            labels, _ = ndimage.label(ok & (heights[n] >= OBJECT_MIN_M))
            sizes = np.bincount(labels.ravel())[1:]
            if int((sizes >= RenderSettings().min_object_m2 / self.gsd_m ** 2).sum()) < CHECK_MIN_OBJECTS:
                continue
            found = check_azimuth(rgb[n][:3], np.where(ok, heights[n], np.nan), self.gsd_m, sun.azimuth_deg, ok)
            if found.found is None or not (found.score >= CHECK_MIN_SCORE):
                self._tries[key] = self._tries.get(key, 0) + 1
                if self._tries[key] >= CHECK_TRIES:  # the image cannot tell: the sun holds, no fit per window
                    self.checked[key] = None
                    return None
                continue
            diff = abs((found.found - sun.azimuth_deg + 180.0) % 360.0 - 180.0)
            note = None
            if diff > CHECK_AZIMUTH_DEG and not found.given_score >= CHECK_RATIO * found.score:
                note = (f"its own shadows fall towards azimuth {found.found:.0f}° on the grid, {diff:.0f}° "
                        f"from the sun the {source} gives ({sun.azimuth_deg:.0f}°): another flight or time; the "
                        "shadow layers are off for it. Pass --acquired TIME (the flight's date and time) or --sun "
                        "AZIMUTH,ELEVATION to map them")
            self.checked[key] = note
            return note
        return None

    def _window(self, rgb: np.ndarray, ok: np.ndarray, height: np.ndarray, spread: np.ndarray | None,
                sun: Sun, workers: int = 1, head: np.ndarray | None = None) -> _Window:
        """The layers of one window: ``rgb`` (3, h, w) colours (:func:`unit_colours`), ``ok`` bool (h, w),
        ``height``/``spread`` float32 (h, w) metres (the network's); fused height and spread only with :attr:`fuse`
        and a measure; ``workers`` threads for the shadow classifier (:meth:`~aerialmtl.sun.ShadowModel.predict_proba`);
        ``head``: the network's P(cast shadow) (h, w), used instead of the classifier where given.
        """
        if head is None:
            p = colour_probability(self.model, rgb, ok, self.gsd_m, workers)
            return window_layers(p, height, spread, sun, self.gsd_m, self.model.threshold, self.fuse)
        return window_layers(head_probability(head, ok), height, spread, sun, self.gsd_m, HEAD_THRESHOLD, self.fuse)

    def _say(self, source: str, why: str) -> None:
        """Warn once per input and cause that some of its valid pixels got no shadow layers."""
        if (source, why) not in self._warned:
            self._warned.add((source, why))
            warnings.warn(f"{source}: no shadow layers where the orthophoto has {why}: shadow.tif and "
                          "shadow_height.tif are nodata there", UserWarning, stacklevel=3)

    def apply(self, stats: McStatistics, rgb: list[np.ndarray], valid: torch.Tensor, sun: Sun | None,
              source: str = "the orthophoto") -> None:
        """Set ``stats.shadow``, ``shadow_on``, ``shadow_height`` and ``shadow_weight`` (B, h, w) for the windows
        ``rgb`` (colours (3, h, w) each, :func:`unit_colours`, in batch order) under ``sun``; with :attr:`fuse`,
        replace ``height_mean`` and ``height_std`` inside measured objects. ``sun`` None: the layers' weights are 0 (the
        stitcher writes nodata) and nothing else changes. ``shadow_on`` is 0 wherever a window's probability is not
        data (:class:`Probability`); ``source`` names the input in the one warning per cause.
        """
        b, h, w = valid.shape
        dev = valid.device
        shadow = torch.zeros((b, h, w), dtype=torch.float32)
        s_on = torch.zeros((b, h, w), dtype=torch.float32)
        s_height = torch.zeros((b, h, w), dtype=torch.float32)
        s_weight = torch.zeros((b, h, w), dtype=torch.float32)
        if sun is not None and stats.height_mean is not None:
            heights = stats.height_mean.detach().float().cpu().numpy().copy()
            spreads = None if stats.height_std is None else stats.height_std.detach().float().cpu().numpy().copy()
            ok_all = valid.cpu().numpy()
            head = None if stats.shadow_head is None else stats.shadow_head.detach().float().cpu().numpy()
            fused = False

            # windows on threads of their own; a lone window (a CPU's batch) spreads its filters over them
            inner = max(1, self.workers // b)

            def one(n: int) -> _Window:
                return self._window(rgb[n][:3], ok_all[n], heights[n], None if spreads is None else spreads[n], sun,
                                    inner, None if head is None else head[n])

            if self.workers > 1 and b > 1:
                with ThreadPoolExecutor(min(self.workers, b), thread_name_prefix="aerialmtl-shadows") as pool:
                    done = list(pool.map(one, range(b)))
            else:
                done = [one(n) for n in range(b)]
            for n, win in enumerate(done):
                if win.why is not None:
                    self._say(source, win.why)
                shadow[n] = torch.from_numpy(win.shadow)
                s_on[n] = torch.from_numpy(win.made.astype(np.float32))
                s_height[n] = torch.from_numpy(win.height)
                s_weight[n] = torch.from_numpy(win.measured.astype(np.float32))
                if win.fused is not None and spreads is not None:
                    heights[n], spreads[n] = win.fused
                    fused = True
            if fused and spreads is not None:  # new tensors: the engine's may be inference-mode views
                stats.height_mean = torch.from_numpy(heights).to(stats.height_mean.device)
                stats.height_std = torch.from_numpy(spreads).to(dev)
        stats.shadow = shadow.to(dev)
        stats.shadow_on = s_on.to(dev)
        stats.shadow_height = s_height.to(dev)
        stats.shadow_weight = s_weight.to(dev)


__all__ = ["HEAD_THRESHOLD", "MIN_CONTRAST", "OBJECT_MIN_M", "Probability", "ShadowStep", "colour_probability",
           "head_probability", "unit_colours", "window_layers"]
