"""One orthophoto as prediction needs it, opened once: :class:`OrthoInput`.

Everything prediction asks of an orthophoto's header — its grid (checked: projected, north-up), the
prediction grid at the model's GSD, whether it has the checkpoint's bands, which of its bands the model
does not read, the window plan — and a sample of its values (like the training data's?
:mod:`aerialmtl.inference.sanity`) is read in one opening by :meth:`OrthoInput.open` and travels with the
input from the job (:mod:`aerialmtl.inference.jobs`) through the predictor to ``prediction.json``. Only
the pixel readers open the file again: one handle per reader thread
(:class:`~aerialmtl.inference.reader.WindowReader`), because a GDAL dataset handle must not be shared
between threads.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rasterio.enums import ColorInterp

from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.inference.sanity import check_input_values
from aerialmtl.inference.windows import Plan, plan_windows
from aerialmtl.io.align import Grid, check_bands, open_raster, ortho_grid, resampled_grid
from aerialmtl.io.fingerprint import changed, input_fingerprint, raster_identity
from aerialmtl.io.paths import is_local

#: Relative GSD difference above which the orthophoto is resampled to the model's GSD.
GSD_TOLERANCE = 0.01


def trained_bands(meta: ModelMeta) -> str:
    """``bands [1, 2, 3] (r, g, b)``: the spectral bands a checkpoint reads, for messages."""
    return f"bands {list(meta.bands)}" + (f" ({', '.join(meta.band_names)})" if meta.band_names else "")


@dataclass(frozen=True)
class OrthoInput:
    """An orthophoto ready to predict with one model.

    Attributes:
        path: the orthophoto as given (a path, or anything GDAL opens).
        native: its own grid.
        grid: the prediction grid: ``native`` resampled to the model's GSD when they differ by more than
            :data:`GSD_TOLERANCE`, else ``native``.
        resampled_from: the orthophoto's GSD (m) when it is resampled, else ``None``.
        count: its number of spectral bands.
        unused_bands: its 1-based bands the model does not read (an alpha band excepted).
        plan: the window plan over ``grid``.
        rescale: ``(a, b)``: the model sees ``a·x + b`` for raw values x (``rescale_input``, see
            :mod:`aerialmtl.inference.sanity`); ``None``: the raw values.
        fingerprint: :func:`~aerialmtl.io.fingerprint.input_fingerprint`, of the file and its sidecars taken
            before the file was first read, with the raster as GDAL presents it (``provenance.input``; checked
            again before the maps are committed, :meth:`changed`).
        tags: its dataset tags (GDAL metadata, e.g. TIFF ``DateTime``: the acquisition time ``--sun auto`` reads).
    """

    path: str | Path
    native: Grid
    grid: Grid
    resampled_from: float | None
    count: int
    unused_bands: tuple[int, ...]
    plan: Plan
    rescale: tuple[float, float] | None = None
    fingerprint: dict[str, Any] | None = None
    tags: dict[str, str] = field(default_factory=dict)

    @classmethod
    def open(cls, path: str | Path, meta: ModelMeta, window: int, overlap: int,
             rescale_input: bool = False) -> OrthoInput:
        """Read what prediction needs from ``path`` in one opening: its header and a sample of its values.

        Args:
            path: the orthophoto.
            meta: the checkpoint metadata (GSD, bands, the training data's value range).
            window, overlap: the window plan's settings.
            rescale_input: map values unlike the training data's onto the training range (:attr:`rescale`)
                instead of refusing them (:func:`~aerialmtl.inference.sanity.check_input_values`).

        Raises:
            AlignmentError: not georeferenced, geographic CRS, no place on Earth (a local CRS, coordinates outside
                its CRS's domain: :func:`~aerialmtl.io.place.check_place`, before any work).
            InputError: the file lacks a band the checkpoint reads, or its values are unlike the training
                data's (the messages name the fix).
        """
        local = input_fingerprint(path) if is_local(path) else None  # stat before the first read
        with open_raster(path, "orthophoto") as src:
            native = ortho_grid(src)
            check_bands(src, meta.bands, "orthophoto", bands_from=f"the checkpoint (trained on {trained_bands(meta)})",
                        fix="predict on an orthophoto with those bands, or train a model on this one's bands "
                            "(`aerialmtl tile --bands ...`)")
            alpha = [i + 1 for i, ci in enumerate(src.colorinterp) if ci == ColorInterp.alpha]
            count = int(src.count)
            rescale = check_input_values(path, meta, rescale_input, dataset=src)
            identity = raster_identity(src)
            tags = dict(src.tags())
        unused = tuple(b for b in range(1, count + 1) if b not in meta.bands and b not in alpha[:1])
        resampled_from = native.gsd if abs(native.gsd - meta.gsd) > GSD_TOLERANCE * meta.gsd else None
        grid = resampled_grid(native, meta.gsd) if resampled_from is not None else native
        fingerprint = {**local, "raster": identity} if local is not None else input_fingerprint(path, identity)
        return cls(path, native, grid, resampled_from, count, unused,
                   plan_windows(grid.height, grid.width, window, overlap), rescale=rescale, fingerprint=fingerprint,
                   tags=tags)

    def changed(self) -> str | None:
        """What changed in the input since it was opened (``None``: nothing; see :attr:`fingerprint`)."""
        if self.fingerprint is None:
            return None
        now = input_fingerprint(self.path, self.fingerprint.get("raster"))  # the files, not the raster again
        return changed(self.fingerprint, now)

    @property
    def name(self) -> str:
        """The file name (for progress bars)."""
        return Path(str(self.path)).name

    def warn_resampled(self, meta: ModelMeta, stacklevel: int = 3) -> None:
        """Warn that the orthophoto is resampled to the model's GSD (when it is)."""
        if self.resampled_from is not None:
            g = meta.gsd
            warnings.warn(
                f"orthophoto '{self.path}' has a GSD of {self.resampled_from:.4g} m but the model was trained at "
                f"{g:.4g} m; resampling the orthophoto to {g:.4g} m (outputs are on the {g:.4g} m grid)",
                stacklevel=stacklevel,
            )

    def warn_unused_bands(self, meta: ModelMeta, stacklevel: int = 3) -> None:
        """Warn when the orthophoto has bands the model does not read."""
        if self.unused_bands:
            warnings.warn(f"orthophoto '{self.path}' has {self.count} bands; the model reads {trained_bands(meta)} "
                          f"as recorded in its checkpoint and ignores band(s) {list(self.unused_bands)}",
                          stacklevel=stacklevel)


__all__ = ["GSD_TOLERANCE", "OrthoInput", "trained_bands"]
