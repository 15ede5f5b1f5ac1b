"""Fingerprints of what GDAL reads.

Whether an input is still the one a run read, and whether a file's bytes are still those written.

An orthophoto is more than its file: GDAL also reads files beside it that change what the raster means, and a
fingerprint that left them out would call a folder complete after its input moved 100 km (a new world file) or
gained a nodata value (a new ``.aux.xml``). :func:`input_fingerprint` covers:

* the file itself: resolved path, size and modification time (ns);
* its **sidecars** (:func:`sidecars`): the STAC item ``NAME.json`` (:data:`SOURCE_SIDECARS`: aerialmtl reads its
  acquisition time, which decides the sun of the shadow layers), world files (``.tfw``, ``.tifw``, ``.tiffw``,
  ``.wld`` and the JPEG/PNG/JPEG 2000 ones, lower or upper case), ``.prj``, the PAM ``.aux.xml`` and ``.aux``,
  external overviews ``.ovr`` and masks ``.msk``: each present one by size and SHA-256 of its content
  (``.ovr``/``.msk``, which can be large, by size and modification time), so that a sidecar that appears, changes
  or goes away changes the fingerprint;
* for a VRT, every source it lists, followed :data:`VRT_DEPTH` levels (:func:`vrt_sources`);
* once the raster is open, what GDAL makes of all that (:func:`raster_identity`): size, geotransform, CRS and
  nodata per band; the completeness check (``--skip-existing``) compares it with the one recorded, so a change
  that no file's date shows is still seen;
* for a remote or virtual path: the GDAL path, what the HTTP server says identifies the version (ETag,
  Last-Modified, size: :func:`http_validators`) or the ``stat`` of a local archive (``/vsizip/`` and the like).

:func:`content_sha256` is the checksum of a file's bytes, streamed (the layers of a prediction folder are
checked by it: :mod:`aerialmtl.formats.prediction`).
"""

from __future__ import annotations

import hashlib
import os
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from aerialmtl.filesafety import open_regular, special_kind
from aerialmtl.io.paths import ARCHIVE_VSI, gdal_path, is_local, local_archive

#: How deep VRTs that list VRTs are followed by :func:`vrt_sources`.
VRT_DEPTH = 4
#: Seconds :func:`http_validators` waits for a server's answer.
HEAD_TIMEOUT = 20.0
#: Sidecars named after the file without its extension (``o.tif`` → ``o.tfw``); world files and projections.
STEM_SIDECARS = (".tfw", ".tifw", ".tiffw", ".wld", ".jgw", ".jpgw", ".pgw", ".pngw", ".j2w", ".prj", ".aux")
#: Sidecars named after the whole file name (``o.tif`` → ``o.tif.aux.xml``).
NAME_SIDECARS = (".aux.xml", ".ovr", ".msk")
#: Sidecars fingerprinted by size and modification time rather than content (they can be as large as the file).
LARGE_SIDECARS = (".ovr", ".msk")
#: Files beside the raster that aerialmtl itself reads, not GDAL (``o.tif`` → ``o.json``, a STAC item whose time
#: decides the sun of the shadow layers): fingerprinted like the sidecars, but no reason to refuse the raster.
SOURCE_SIDECARS = (".json",)


def content_sha256(path: str | Path, chunk: int = 1 << 22) -> str:
    """The SHA-256 (hex) of the bytes of file ``path``, read in ``chunk``-byte pieces (not held in memory).

    Raises:
        OSError: it cannot be read, or it is not a regular file (a FIFO, a device: never waited on or read
            without end; :func:`aerialmtl.filesafety.open_regular`).
    """
    h = hashlib.sha256()
    buf = bytearray(chunk)
    view = memoryview(buf)
    with os.fdopen(open_regular(path, follow_links=True), "rb", buffering=0) as f:  # a FIFO there: an error, no hang
        while n := f.readinto(buf):
            h.update(view[:n])
    return h.hexdigest()


def file_fingerprint(path: str | Path | None) -> dict[str, Any] | None:
    """Resolved path, size and mtime (ns) of a local file (``None`` for ``None``); the GDAL path alone otherwise."""
    if path is None:
        return None

    if not is_local(path):
        return {"path": gdal_path(path)}
    st = os.stat(path)
    return {"path": str(Path(path).resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def sidecar_paths(path: str | Path) -> list[Path]:
    """The files GDAL may read beside local raster ``path`` (present or not), see the module docstring."""
    p = Path(path)
    out: list[Path] = []
    for suffix in STEM_SIDECARS:
        out += [p.with_suffix(suffix), p.with_suffix(suffix.upper())]
    for suffix in NAME_SIDECARS:
        out += [p.with_name(p.name + suffix), p.with_name(p.name + suffix.upper())]
    return list(dict.fromkeys(x for x in out if x != p))


def sidecars(path: str | Path) -> dict[str, dict[str, Any]]:
    """File name → fingerprint of each sidecar present beside local raster ``path`` (see the module docstring).

    A sidecar that is not a regular file (a folder, a FIFO) is recorded as such and never opened.
    """
    out: dict[str, dict[str, Any]] = {}
    p = Path(path)
    for side in [*sidecar_paths(path), *(p.with_suffix(s) for s in SOURCE_SIDECARS if p.suffix.lower() != s)]:
        try:
            st = os.stat(side)
        except OSError:
            continue
        if not stat.S_ISREG(st.st_mode):
            out[side.name] = {"kind": stat.filemode(st.st_mode)[0]}
            continue
        if side.name.lower().endswith(LARGE_SIDECARS):
            out[side.name] = {"size": st.st_size, "mtime_ns": st.st_mtime_ns}
            continue
        try:
            out[side.name] = {"size": st.st_size, "sha256": content_sha256(side)}
        except OSError as exc:
            out[side.name] = {"size": st.st_size, "unreadable": exc.strerror or str(exc)}
    return out


def blocking_file(path: str | Path, depth: int = VRT_DEPTH) -> tuple[Path, str] | None:
    """The first file of raster ``path`` that is a FIFO, a socket or a device, and what it is; ``None`` if none.

    Looked at: local raster ``path``, the sidecars GDAL reads when it opens it (:func:`sidecar_paths`) and, for a
    VRT, the files it lists (``depth`` levels), links followed. GDAL opens those without a timeout and would wait
    on a FIFO forever, so a raster with one is not opened (:func:`aerialmtl.io.align.open_raster`). A folder at a
    sidecar's name is not one (GDAL reads nothing there).
    """
    for p in (Path(path), *sidecar_paths(path)):
        try:
            mode = os.stat(p).st_mode
        except OSError:
            continue
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            return p, special_kind(mode)
    if str(path).lower().endswith(".vrt") and depth > 0:  # and the files a VRT lists, which GDAL opens as it reads
        for name in _vrt_source_names(path):
            found = blocking_file(name, depth - 1) if is_local(name) else None
            if found is not None:
                return found
    return None


def raster_identity(src: Any) -> dict[str, Any]:
    """What GDAL makes of an open raster ``src`` (a rasterio dataset).

    Size (px), geotransform, CRS, nodata per band (as text: NaN is no JSON number). The same file and sidecars
    always give the same identity.
    """
    crs = src.crs.to_string() if src.crs is not None else None
    return {"width": int(src.width), "height": int(src.height), "transform": [float(v) for v in src.transform][:6],
            "crs": crs, "nodata": [None if v is None else repr(float(v)) for v in src.nodatavals]}


def _vrt_source_names(path: str | Path) -> list[str]:
    """The sources local VRT ``path`` lists (``SourceFilename``), in document order without repeats.

    Relative ones are resolved against its folder; ``[]`` when it cannot be read (a FIFO there is not waited on).
    """
    import xml.etree.ElementTree as ET

    try:
        with os.fdopen(open_regular(path, follow_links=True), "rb") as fh:
            root = ET.parse(fh).getroot()
    except (OSError, ET.ParseError):
        return []
    out: list[str] = []
    for el in root.iter("SourceFilename"):
        name = (el.text or "").strip()
        if is_local(name) and el.get("relativeToVRT", "0") == "1":
            name = str(Path(path).parent / name)
        if name and name not in out:
            out.append(name)
    return out


def vrt_sources(path: str | Path, depth: int = VRT_DEPTH) -> list[dict[str, Any]]:
    """:func:`input_fingerprint` of every source a local VRT lists, in document order without repeats.

    ``SourceFilename``, relative ones resolved against the VRT's folder; VRTs inside followed ``depth`` levels.
    """
    out: list[dict[str, Any]] = []
    for name in _vrt_source_names(path):
        try:
            fp = input_fingerprint(name, depth=depth - 1) if depth > 0 else file_fingerprint(name)
        except OSError:
            fp = {"path": name, "missing": True}
        if fp is not None:
            out.append(fp)
    return out


def http_validators(url: str) -> dict[str, Any] | None:
    """What an HTTP(S) server says identifies the current version of ``url`` (one HEAD request).

    ``etag``, ``last_modified`` and ``size`` (bytes); ``None`` when it does not answer or the URL is not HTTP(S).
    """
    import urllib.error
    import urllib.request

    if url.startswith("/vsicurl/"):
        url = url[len("/vsicurl/"):]
    if not url.lower().startswith(("http://", "https://")):
        return None
    req = urllib.request.Request(url, method="HEAD")
    try:
        with urllib.request.urlopen(req, timeout=HEAD_TIMEOUT) as resp:  # noqa: S310 - http(s) only, checked above
            headers = resp.headers
    except (urllib.error.URLError, OSError, ValueError):
        return None
    size = headers.get("Content-Length")
    return {"etag": headers.get("ETag"), "last_modified": headers.get("Last-Modified"),
            "size": int(size) if size and size.isdigit() else None}


def input_fingerprint(path: str | Path, raster: Mapping[str, Any] | None = None,
                      depth: int = VRT_DEPTH) -> dict[str, Any]:
    """The fingerprint of an orthophoto: what says whether what GDAL reads is still the same.

    See the module docstring.

    Args:
        path: the orthophoto (a local file, a VRT, a URL or a GDAL ``/vsi...`` path).
        raster: its :func:`raster_identity`, once it is open (recorded under ``raster``).
        depth: how many levels of VRTs inside VRTs are followed.

    Returns:
        For a local file, :func:`file_fingerprint` plus ``sidecars`` (and ``sources`` for a VRT); otherwise the
        GDAL path and ``server`` (the HTTP validators) or ``archive`` (the local archive's
        :func:`file_fingerprint`); with ``raster`` when given.
    """
    fp = file_fingerprint(path)
    assert fp is not None
    if is_local(path):
        fp["sidecars"] = sidecars(path)
        if str(path).lower().endswith(".vrt"):
            fp["sources"] = vrt_sources(path, depth)
    else:
        text = gdal_path(path)
        archive = local_archive(text)
        if archive is not None:
            fp["archive"] = file_fingerprint(archive)
        elif not text.startswith(ARCHIVE_VSI):
            server = http_validators(text)
            if server is not None:
                fp["server"] = server
    if raster is not None:
        fp["raster"] = dict(raster)
    return fp


def changed(before: Mapping[str, Any], after: Mapping[str, Any]) -> str | None:
    """What differs between two fingerprints (:func:`input_fingerprint`) of one input (``None``: nothing).

    For example ``"sidecar o.tfw changed"``, ``"raster.transform [...] → [...]"``.
    """
    if before == after:
        return None
    parts: list[str] = []
    for key in sorted(set(before) | set(after)):
        old, new = before.get(key), after.get(key)
        if old == new:
            continue
        if key == "sidecars" and isinstance(old, dict) and isinstance(new, dict):
            for name in sorted(set(old) | set(new)):
                if old.get(name) != new.get(name):
                    what = "appeared" if name not in old else "went away" if name not in new else "changed"
                    parts.append(f"sidecar {name} {what}")
        elif key == "raster" and isinstance(old, dict) and isinstance(new, dict):
            parts += [f"raster {k} {old.get(k)!r} → {new.get(k)!r}" for k in sorted(set(old) | set(new))
                      if old.get(k) != new.get(k)]
        elif key in ("sources", "server", "archive"):
            parts.append(f"its {key}")
        else:
            parts.append(f"{key} {old!r} → {new!r}")
    return ", ".join(parts)


__all__ = ["HEAD_TIMEOUT", "LARGE_SIDECARS", "NAME_SIDECARS", "SOURCE_SIDECARS", "STEM_SIDECARS", "VRT_DEPTH",
           "blocking_file", "changed", "content_sha256", "file_fingerprint", "http_validators", "input_fingerprint",
           "raster_identity", "sidecar_paths", "sidecars", "vrt_sources"]
