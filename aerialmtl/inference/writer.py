"""Streaming, all-or-nothing writer of the prediction folder.

Each output layer (:class:`~aerialmtl.formats.prediction.LayerSpec`) is first written into a hidden
staging GeoTIFF in the output folder (``.height.tif.staging``; ``.height.tif.staging-<row>`` for the
strip of rows one process of a distributed run computes). Staging files are raw (uncompressed) tiled
GeoTIFFs: the stitcher's finished blocks are written as they come, in any shape, by a background
thread while the model runs, and GDAL rewrites a partly written tile in place, so nothing is buffered
(memory does not grow with the raster) and no compression is paid twice. :meth:`PredictionWriter.convert`
turns every layer into a COG (``.height.tif.partial``; the layers in parallel, each compressed on
several threads; strips of several processes are first joined by a VRT); :meth:`PredictionWriter.publish`
writes each layer's QGIS style (:mod:`aerialmtl.formats.qgis_style`, its range from the COG's overviews),
the STAC ``item.json`` (:mod:`aerialmtl.formats.stac`) and ``prediction.json`` (the run's
:class:`~aerialmtl.formats.prediction.PredictionRecord`, written once), and only then renames everything
to the final names, ``prediction.json`` last: an interrupted run leaves no file at a final path, and a
folder with ``prediction.json`` is complete. :meth:`PredictionWriter.abort` removes the hidden files it wrote.

The writer owns only its own staging files. The folder is the job's (:class:`~aerialmtl.inference.job.InputJob`):
it creates it, claims its outputs, removes a killed run's leftovers and an earlier run's stale layers, and
removes the folder again when a failed run created it.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, NoReturn

import rasterio
from rasterio.errors import RasterioError
from rasterio.windows import Window

from aerialmtl import runtime
from aerialmtl.errors import OutputError, cause
from aerialmtl.filesafety import staging_path
from aerialmtl.formats.prediction import (
    INFO_FILE,
    ITEM_FILE,
    LayerSpec,
    PredictionRecord,
    style_filename,
)
from aerialmtl.formats.qgis_style import layer_style, write_style
from aerialmtl.formats.stac import build_item, write_json
from aerialmtl.inference.stitch import Block
from aerialmtl.io.align import Grid
from aerialmtl.io.cog import staging_profile, to_cog
from aerialmtl.io.fingerprint import content_sha256
from aerialmtl.io.oserrors import kind_of, output_error
from aerialmtl.io.outputs import MERGE_VRT, STAGING
from aerialmtl.io.stats import BandStats, band_stats
from aerialmtl.io.vrt import mosaic_vrt

#: Blocks queued for the writer thread at most (the model waits beyond; memory stays bounded).
MAX_PENDING_BLOCKS = 4
#: DEFLATE level of the COGs: 1 writes 1.1-2x faster than GDAL's default 6 for 1-4 % larger files on float
#: heights (bench/RESULTS.md, predict); None = GDAL's default.
COG_LEVEL: int | None = 1


def cog_threads() -> int:
    """Threads for COG compression: the CPUs this process may use (:func:`aerialmtl.runtime.usable_cpus`)."""
    return runtime.usable_cpus()


def _staging_tag(row_start: int | None) -> str:
    """Tag of a layer's staging file: the whole raster, or the strip starting at grid row ``row_start``."""
    return STAGING if row_start is None else f"{STAGING}-{row_start}"


def _apply_metadata(dst: Any, spec: LayerSpec) -> None:
    """Band descriptions, units, colour table and tags of ``spec`` on an open dataset."""
    for b, desc in enumerate(spec.descriptions, start=1):
        dst.set_band_description(b, desc)
    if spec.units:
        dst.units = spec.units
        for b, unit in enumerate(spec.units, start=1):
            if unit:
                dst.update_tags(b, units=unit)
    if spec.colormap is not None:
        dst.write_colormap(1, spec.colormap)
    if spec.tags:
        dst.update_tags(**spec.tags)
    for b, tags in spec.band_tags.items():
        dst.update_tags(b, **tags)


def _writable_error(out_dir: Path, exc: BaseException) -> OutputError:
    if kind_of(exc, out_dir) is not None:  # a full disk or a read-only folder: said as every command says it
        return output_error(exc, out_dir, "the prediction folder", "‹out_dir›")
    return OutputError(
        f"cannot write in output folder '{out_dir}' ({cause(exc)}); "
        "choose a writable ‹out_dir› with free space"
    )


class PredictionWriter:
    """Write the layers of one prediction folder; see the module docstring.

    Args:
        out_dir: the prediction folder (the job creates it).
        grid: the reference grid (CRS, transform, size of every output).
        specs: the layers to write.
        rows: write only grid rows ``[start, stop)`` (one strip of a distributed run): the staging files
            are then named after ``start``, and only the process that calls :meth:`convert` with every
            strip converts them. Default: the whole grid.

    Raises:
        OutputError: the folder cannot be created or written.
    """

    def __init__(self, out_dir: str | Path, grid: Grid, specs: Sequence[LayerSpec],
                 rows: tuple[int, int] | None = None) -> None:
        self.out_dir = Path(out_dir)
        self.grid = grid
        self.specs = {s.name: s for s in specs}
        self.rows = rows or (0, grid.height)
        self._strip_start = None if rows is None else rows[0]
        self._datasets: dict[str, Any] = {}
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="aerialmtl-writer")
        self._pending: list[Future[None]] = []
        self._slots = threading.BoundedSemaphore(MAX_PENDING_BLOCKS)
        self._partials: dict[str, tuple[Path, Path]] = {}  # converted: key → (hidden file, final path)
        self._stats: dict[str, BandStats | None] = {}
        self._extras: set[str] = set()  # keys of the styles and item.json among the staged files
        self.seconds_writing = 0.0
        try:
            r0, r1 = self.rows
            transform = grid.window_transform(Window(0, r0, grid.width, r1 - r0))
            for s in specs:
                profile = staging_profile(grid.crs, transform, grid.width, r1 - r0, s.count, s.dtype, s.nodata,
                                          compress=False)
                dst = rasterio.open(self.staging(s.name), "w", **profile)
                self._datasets[s.name] = dst
                _apply_metadata(dst, s)
        except BaseException as exc:
            self._fail(exc)

    def staging(self, name: str, row_start: int | None = -1) -> Path:
        """Staging path of layer ``name`` (of this writer's strip by default)."""
        start = self._strip_start if row_start == -1 else row_start
        return staging_path(self.out_dir / self.specs[name].filename, _staging_tag(start))

    # ---- writing ----------------------------------------------------------------------------------
    def write(self, block: Block) -> None:
        """Queue a finished block for the writer thread (waits while :data:`MAX_PENDING_BLOCKS` are queued).

        Raises whatever an earlier queued write raised.
        """
        self._raise_done()
        self._slots.acquire()
        try:
            self._pending.append(self._pool.submit(self._write, block))
        except BaseException:
            self._slots.release()
            raise

    def _write(self, block: Block) -> None:
        import time

        t0 = time.perf_counter()
        try:
            win = Window(block.col_off, block.row_off - self.rows[0], block.width, block.height)
            for name, dst in self._datasets.items():
                dst.write(block.layers[name], window=win)
        finally:
            self._slots.release()
            self.seconds_writing += time.perf_counter() - t0

    def _raise_done(self, wait: bool = False) -> None:
        keep = []
        for fut in self._pending:
            if wait or fut.done():
                exc = fut.exception()
                if exc is not None:
                    self._pending = []
                    if isinstance(exc, (OSError, RasterioError)) and not isinstance(exc, OutputError):
                        raise _writable_error(self.out_dir, exc) from exc
                    raise exc
            else:
                keep.append(fut)
        self._pending = keep

    def finish(self) -> dict[str, Path]:
        """Wait for the queued blocks and close the staging files; returns layer name → staging path."""
        try:
            self._raise_done(wait=True)
        finally:
            for dst in self._datasets.values():
                if not dst.closed:
                    dst.close()
        self._pool.shutdown(wait=True)
        return {name: self.staging(name) for name in self.specs}

    # ---- committing -------------------------------------------------------------------------------
    def _fail(self, exc: BaseException) -> NoReturn:
        """Remove this run's hidden files and raise ``exc`` (an OS error as the one-line :class:`OutputError`)."""
        self.abort()
        if isinstance(exc, (OSError, RasterioError)) and not isinstance(exc, OutputError):
            raise _writable_error(self.out_dir, exc) from exc
        raise exc

    def convert(self, strips: Sequence[int] = ()) -> None:
        """Convert every layer to a hidden COG (``.NAME.partial``) and delete the staging files.

        Args:
            strips: first rows of the other strips of a distributed run (their staging files, written
                by other processes, are joined with this writer's through a VRT).
        """
        merged: list[Path] = []
        try:
            self.finish()
            starts = sorted({self.rows[0], *strips})
            stagings = {n: [self.staging(n)] if len(starts) == 1 else [self.staging(n, s) for s in starts]
                        for n in self.specs}
            sources: dict[str, Path] = {}
            for name, spec in self.specs.items():
                if len(starts) == 1:
                    sources[name] = stagings[name][0]
                else:
                    vrt = staging_path(self.out_dir / spec.filename, MERGE_VRT)
                    mosaic_vrt(vrt, stagings[name], categorical=spec.categorical, overviews=False)
                    merged.append(vrt)
                    sources[name] = vrt
            threads = cog_threads()

            def convert(name: str) -> tuple[str, Path]:
                spec = self.specs[name]
                partial = staging_path(self.out_dir / spec.filename)
                to_cog(sources[name], partial, categorical=spec.categorical, level=COG_LEVEL, num_threads=threads)
                # from the COG's overviews: the display range of the style, the statistics of the STAC item
                self._stats[name] = None if spec.categorical else band_stats(partial)
                return name, partial

            with ThreadPoolExecutor(max_workers=max(1, len(self.specs)), thread_name_prefix="aerialmtl-cog") as pool:
                futures = [pool.submit(convert, n) for n in self.specs]
                for fut in futures:
                    name, partial = fut.result()
                    self._partials[name] = (partial, self.out_dir / self.specs[name].filename)
            for paths in stagings.values():
                for path in paths:
                    path.unlink(missing_ok=True)
        except BaseException as exc:
            for vrt in merged:
                vrt.unlink(missing_ok=True)
            self._fail(exc)
        for vrt in merged:
            vrt.unlink(missing_ok=True)

    def stage(self, record: PredictionRecord) -> list[str]:
        """Write the styles, ``item.json`` and ``prediction.json`` (``record`` with ``created``, ``files`` and
        ``file_sizes`` added) as hidden files beside those of :meth:`convert`.

        Returns:
            the final names of every file :meth:`publish` will put in place.
        """
        partials = self._partials
        try:
            now = datetime.now(timezone.utc).replace(microsecond=0)
            record = record.model_copy(update={"created": now.isoformat()})
            extras = self._write_metadata(record, self._stats)
            partials.update(extras)
            self._extras = set(extras)
            record = record.model_copy(update={
                "files": {n: p.name for n, (_, p) in partials.items()},
                # the layers' sizes; the styles and item.json are the user's to edit (QGIS "Save as
                # default", a STAC datetime) without making the folder look incomplete
                "file_sizes": {p.name: tmp.stat().st_size for k, (tmp, p) in partials.items() if k not in extras},
                # and their content, which --skip-existing checks (a zeroed block keeps the size)
                "file_sha256": {p.name: content_sha256(tmp) for k, (tmp, p) in partials.items() if k not in extras}})
            js = staging_path(self.out_dir / INFO_FILE)
            js.write_text(record.to_json(), encoding="utf-8")
            partials["prediction"] = (js, self.out_dir / INFO_FILE)
        except BaseException as exc:
            self._fail(exc)
        return [p.name for _, p in partials.values()]

    def publish(self) -> dict[str, Path]:
        """Rename every staged file (:meth:`convert`, :meth:`stage`) to its final name, ``prediction.json`` last.

        Returns:
            layer name → final path (``"prediction"`` for the JSON file).
        """
        for tmp, final in self._partials.values():  # prediction.json last: its presence marks a complete folder
            os.replace(tmp, final)
        return {n: final for n, (_, final) in self._partials.items() if n not in self._extras}

    def _write_metadata(self, record: PredictionRecord,
                        stats: dict[str, BandStats | None]) -> dict[str, tuple[Path, Path]]:
        """The QGIS style of every layer and the STAC item, as hidden partial files.

        Returns:
            key → (partial path, final path): ``<layer>_style`` and ``item``.
        """
        out: dict[str, tuple[Path, Path]] = {}
        for name, spec in self.specs.items():
            qml = staging_path(self.out_dir / style_filename(name))
            out[f"{name}_style"] = (write_style(qml, layer_style(spec, stats.get(name)), atomic=False),
                                    self.out_dir / style_filename(name))
        item = build_item(self.out_dir, self.grid, list(self.specs.values()), record.model_dump(), stats)
        out["item"] = (write_json(staging_path(self.out_dir / ITEM_FILE), item, atomic=False),
                       self.out_dir / ITEM_FILE)
        return out

    def abort(self) -> None:
        """Close and delete the hidden files of this run (final paths are never touched)."""
        for fut in self._pending:
            fut.cancel()
        self._pool.shutdown(wait=True)
        self._pending = []
        for dst in self._datasets.values():
            try:
                if not dst.closed:
                    dst.close()
            except Exception:  # pragma: no cover - best effort cleanup
                pass
        for name in self.specs:  # this writer's own files only: other processes may still be writing theirs
            self.staging(name).unlink(missing_ok=True)
        for tmp, _ in self._partials.values():
            tmp.unlink(missing_ok=True)


__all__ = ["PredictionWriter"]
