"""Streaming, all-or-nothing writer of the prediction folder.

Each output layer is written row band by row band into a hidden staging GeoTIFF in the output folder
(``.height.tif.staging``); rows are buffered until whole 512-pixel block rows are complete so GDAL
never holds half-written tiles. :meth:`PredictionWriter.commit` converts every staging file into a
COG (``.height.tif.partial``) and only then renames all of them to their final names, so an
interrupted run leaves no file at a final path. :meth:`PredictionWriter.abort` removes the hidden files
(and the folder, if this run created it and it is empty); hidden files that a killed run could not
remove are deleted when the next run into the same folder starts, so a plain re-run completes.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.errors import RasterioError
from rasterio.windows import Window

from aerialmtl.errors import OutputError, OutputExistsError
from aerialmtl.formats.prediction import ALL_FILES
from aerialmtl.inference.stitch import FinalRows
from aerialmtl.io.align import Grid
from aerialmtl.io.cog import COG_BLOCKSIZE, staging_profile, to_cog
from aerialmtl.io.outputs import make_output_dir

#: Every file name a prediction folder can hold (removed on --overwrite when this run does not write it).
ALL_OUTPUTS = ALL_FILES


@dataclass(frozen=True)
class LayerSpec:
    """One output raster.

    Attributes:
        name: layer name (file ``<name>.tif``).
        count, dtype, nodata: bands, numpy dtype name, nodata value.
        descriptions: one description per band.
        units: unit per band (``"m"``, ``"nats"``, ...; empty for none).
        categorical: class indices (``mode`` overviews) rather than continuous values.
        colormap: optional GDAL colour table of band 1.
        tags: dataset tags; ``band_tags``: tags per band (1-based index → mapping).
    """

    name: str
    count: int
    dtype: str
    nodata: float | int
    descriptions: tuple[str, ...]
    units: tuple[str, ...] = ()
    categorical: bool = False
    colormap: dict[int, tuple[int, int, int, int]] | None = None
    tags: dict[str, str] = field(default_factory=dict)
    band_tags: dict[int, dict[str, str]] = field(default_factory=dict)

    @property
    def filename(self) -> str:
        return f"{self.name}.tif"


class _Layer:
    def __init__(self, spec: LayerSpec, grid: Grid, staging: Path) -> None:
        self.spec = spec
        self.staging = staging
        profile = staging_profile(grid.crs, grid.transform, grid.width, grid.height, spec.count, spec.dtype,
                                  spec.nodata)
        self.dst = rasterio.open(staging, "w", **profile)
        for b, desc in enumerate(spec.descriptions, start=1):
            self.dst.set_band_description(b, desc)
        if spec.units:
            self.dst.units = spec.units
            for b, unit in enumerate(spec.units, start=1):
                if unit:
                    self.dst.update_tags(b, units=unit)
        if spec.colormap is not None:
            self.dst.write_colormap(1, spec.colormap)
        if spec.tags:
            self.dst.update_tags(**spec.tags)
        for b, tags in spec.band_tags.items():
            self.dst.update_tags(b, **tags)
        self.pending: list[np.ndarray] = []
        self.pending_start = 0
        self.width = grid.width
        self.height = grid.height

    def write(self, row_start: int, data: np.ndarray) -> None:
        """Queue rows ``[row_start, row_start + h)``; write every complete block row."""
        if not self.pending:
            self.pending_start = row_start
        self.pending.append(data)
        stop = row_start + data.shape[1]
        cut = stop if stop >= self.height else (stop // COG_BLOCKSIZE) * COG_BLOCKSIZE
        if cut > self.pending_start:
            buf = np.concatenate(self.pending, axis=1) if len(self.pending) > 1 else self.pending[0]
            n = cut - self.pending_start
            self.dst.write(buf[:, :n], window=Window(0, self.pending_start, self.width, n))
            rest = buf[:, n:]
            self.pending = [rest] if rest.shape[1] else []
            self.pending_start = cut

    def close(self) -> None:
        if self.pending:  # pragma: no cover - the last band always reaches the bottom row
            buf = np.concatenate(self.pending, axis=1)
            self.dst.write(buf, window=Window(0, self.pending_start, self.width, buf.shape[1]))
            self.pending = []
        self.dst.close()


def hidden(out_dir: Path, filename: str, suffix: str) -> Path:
    return out_dir / f".{filename}.{suffix}"


def check_outputs_free(out_dir: Path, filenames: list[str], overwrite: bool) -> None:
    """Raise :class:`OutputExistsError` if any output already exists and ``overwrite`` is false."""
    existing = [f for f in filenames if (out_dir / f).exists()]
    if existing and not overwrite:
        raise OutputExistsError(
            f"output folder '{out_dir}' already holds {', '.join(existing)}; pass --overwrite to replace them "
            "or choose another --out folder"
        )


def remove_leftovers(out_dir: Path) -> None:
    """Delete hidden staging/partial files that a killed run (SIGKILL, power loss) left in ``out_dir``.

    They never sit at a final path, so they are only clutter; a new run writes its own from scratch.
    """
    for name in ALL_OUTPUTS:
        for suffix in ("staging", "partial"):
            try:
                hidden(out_dir, name, suffix).unlink(missing_ok=True)
            except OSError:  # pragma: no cover - e.g. a read-only folder; writing will say so
                pass


class PredictionWriter:
    """Write the layers of one prediction folder; see the module docstring.

    Args:
        out_dir: the prediction folder (created if missing).
        grid: the reference grid (CRS, transform, size of every output).
        specs: the layers to write.
        overwrite: replace existing outputs (and remove outputs of earlier runs this run does not write).

    Raises:
        OutputExistsError: an output exists and ``overwrite`` is false.
        OutputError: the folder cannot be created.
    """

    def __init__(self, out_dir: str | Path, grid: Grid, specs: list[LayerSpec], overwrite: bool = False) -> None:
        self.out_dir = Path(out_dir)
        self.grid = grid
        self.specs = {s.name: s for s in specs}
        self.overwrite = overwrite
        check_outputs_free(self.out_dir, [s.filename for s in specs] + ["prediction.json"], overwrite)
        self._created_dir = make_output_dir(self.out_dir)
        self._layers: dict[str, _Layer] = {}
        remove_leftovers(self.out_dir)
        try:
            for s in specs:
                self._layers[s.name] = _Layer(s, grid, hidden(self.out_dir, s.filename, "staging"))
        except Exception as exc:
            self.abort()
            if isinstance(exc, (OSError, RasterioError)) and not isinstance(exc, OutputError):
                raise OutputError(
                    f"cannot write in output folder '{self.out_dir}' ({' '.join(str(exc).split())[:160]}); "
                    "choose a writable --out with free space"
                ) from exc
            raise

    def write(self, rows: FinalRows) -> None:
        """Write finished rows (every layer in ``rows.layers`` that this writer owns)."""
        for name, layer in self._layers.items():
            layer.write(rows.row_start, rows.layers[name])

    def commit(self, info: dict[str, Any]) -> dict[str, Path]:
        """Convert every layer to a COG, write ``prediction.json``, then rename all to their final names.

        Returns:
            name → final path (``"prediction"`` for the JSON file).
        """
        partials: dict[str, tuple[Path, Path]] = {}
        try:
            for name, layer in self._layers.items():
                layer.close()
            for name, layer in self._layers.items():
                partial = hidden(self.out_dir, layer.spec.filename, "partial")
                to_cog(layer.staging, partial, categorical=layer.spec.categorical)
                layer.staging.unlink()
                partials[name] = (partial, self.out_dir / layer.spec.filename)
            info = dict(info, files={n: p.name for n, (_, p) in partials.items()})
            js = hidden(self.out_dir, "prediction.json", "partial")
            js.write_text(json.dumps(info, indent=2, default=str), encoding="utf-8")
            partials["prediction"] = (js, self.out_dir / "prediction.json")
        except BaseException:
            for tmp, _ in partials.values():
                tmp.unlink(missing_ok=True)
            self.abort()
            raise
        if self.overwrite:  # outputs of an earlier run that this run does not produce would be stale
            produced = {p.name for _, p in partials.values()}
            for f in ALL_OUTPUTS:
                if f not in produced:
                    (self.out_dir / f).unlink(missing_ok=True)
        for tmp, final in partials.values():
            os.replace(tmp, final)
        return {n: final for n, (_, final) in partials.items()}

    def abort(self) -> None:
        """Close and delete every hidden file of this run (final paths are never touched)."""
        for layer in self._layers.values():
            try:
                if not layer.dst.closed:
                    layer.dst.close()
            except Exception:  # pragma: no cover - best effort cleanup
                pass
        remove_leftovers(self.out_dir)
        if self._created_dir:  # leave no empty folder behind either
            try:
                self.out_dir.rmdir()
            except OSError:
                pass


__all__ = ["ALL_OUTPUTS", "LayerSpec", "PredictionWriter", "check_outputs_free", "remove_leftovers"]
