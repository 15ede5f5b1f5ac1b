"""Input rasters are GDAL paths: local files, VRTs, URLs and ``/vsi...`` virtual paths.

Every command that reads rasters (predict, tile, evaluate) takes its inputs as strings and hands them to
GDAL unchanged but for URL schemes, which become GDAL's virtual file systems:

==================================  ==========================================
given                               opened as
==================================  ==========================================
``ortho.tif``, ``mosaic.vrt``       itself (a local file)
``https://host/o.tif`` (``http``)   ``/vsicurl/https://host/o.tif``
``s3://bucket/key.tif``             ``/vsis3/bucket/key.tif`` (AWS credentials or ``AWS_NO_SIGN_REQUEST=YES``)
``gs://bucket/key.tif``             ``/vsigs/bucket/key.tif``
``az://container/key.tif``          ``/vsiaz/container/key.tif``
``/vsicurl/...``, ``/vsizip/...``   itself
==================================  ==========================================

``pathlib.Path`` is never used on such strings: it folds ``s3://b/x`` into ``s3:/b/x`` and
``/vsicurl/https://h`` into ``/vsicurl/https:/h``. The GDAL settings that keep remote reads fast and
quiet are set once here (:func:`configure_remote`); a user's own environment variables win.
"""

from __future__ import annotations

import os
import re
from pathlib import Path, PurePosixPath

#: URL scheme → GDAL virtual file system prefix (``https://h/x`` keeps its scheme under ``/vsicurl/``).
SCHEMES: dict[str, str] = {
    "http": "/vsicurl/", "https": "/vsicurl/", "ftp": "/vsicurl/",
    "s3": "/vsis3/", "gs": "/vsigs/", "az": "/vsiaz/",
}
#: GDAL virtual file systems that read over the network.
NETWORK_VSI = ("/vsicurl", "/vsis3", "/vsigs", "/vsiaz", "/vsiadls", "/vsioss", "/vsiswift", "/vsiwebhdfs",
               "/vsihdfs")

#: GDAL settings for remote inputs (applied unless the environment already sets them; the no-listing open is
#: :data:`REMOTE_OPEN_OPTIONS`): the tiles a window needs fetched one range after the other through GDAL's
#: download cache (``GDAL_HTTP_MULTIRANGE=SERIAL``; GDAL's default parallel multi-range reads bypass that
#: cache, so the COG tiles two overlapping window rows share were downloaded twice: 28 MiB instead of
#: 16 MiB for a 15 MiB COG, bench/RESULTS.md, remote inputs), in 1 MiB chunks, with a 128 MiB cache shared
#: by the reader threads; neighbouring ranges merged into one request; and a few retries on the temporary
#: HTTP errors (429, 502-504) object stores answer under load.
REMOTE_GDAL_OPTIONS: dict[str, str] = {
    "GDAL_HTTP_MULTIRANGE": "SERIAL",
    "CPL_VSIL_CURL_CACHE_SIZE": str(128 * 2**20),
    "VSI_CACHE": "TRUE",
    "GDAL_HTTP_MERGE_CONSECUTIVE_RANGES": "YES",
    "GDAL_HTTP_MULTIPLEX": "YES",
    "GDAL_HTTP_MAX_RETRY": "3",
    "GDAL_HTTP_RETRY_DELAY": "1",
    "GDAL_HTTP_TIMEOUT": "60",
    "CPL_VSIL_CURL_CHUNK_SIZE": "1048576",
}

_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)://(.*)$", re.S)


def gdal_path(path: str | os.PathLike[str]) -> str:
    """The path GDAL opens for ``path`` (see the module table); local paths are returned as given."""
    text = os.fspath(path)
    match = _SCHEME.match(text)
    if match is None:
        return text
    scheme = match.group(1).lower()
    prefix = SCHEMES.get(scheme)
    if prefix is None:
        return text  # GDAL decides (and says what it cannot open)
    return prefix + (text if prefix == "/vsicurl/" else match.group(2))


def is_remote(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is read over the network (a URL, ``/vsicurl/``, ``/vsis3/``, ... at any depth)."""
    text = gdal_path(path)
    return any(f"{vsi}/" in text for vsi in NETWORK_VSI)


def is_local(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a plain file of this machine's file system (which can be ``stat``-ed).

    URLs and every ``/vsi...`` path (also ``/vsizip/`` over a local archive) are not: callers that
    fingerprint or check files by their size and time must treat them otherwise.
    """
    text = gdal_path(path)
    return not text.startswith("/vsi")


def raster_name(path: str | os.PathLike[str]) -> str:
    """The file name of ``path`` (``o.tif`` for ``https://h/a/o.tif?sig=...`` or ``/vsizip/a.zip/o.tif``)."""
    text = gdal_path(path)
    if is_local(text):
        return Path(text).name
    text = text.split("?", 1)[0].rstrip("/")
    return PurePosixPath(text).name


def raster_stem(path: str | os.PathLike[str]) -> str:
    """:func:`raster_name` without its extension (``o`` for ``.../o.tif``)."""
    name = raster_name(path)
    stem = PurePosixPath(name).stem
    return stem or name


def recorded_path(path: str | os.PathLike[str]) -> str:
    """``path`` as provenance records it: a local file made absolute, anything else in GDAL's spelling."""
    text = gdal_path(path)
    return str(Path(text).resolve()) if is_local(text) else text


#: GDAL's archive file systems whose archive can be a local file (``/vsizip/a.zip/x.tif``).
ARCHIVE_VSI = ("/vsizip/", "/vsitar/", "/vsigzip/", "/vsi7z/", "/vsirar/")


def archive_parts(path: str) -> tuple[str, str] | None:
    """``(archive, member)`` of a ``/vsizip/``-like path over a local archive (``/vsizip//d/a.zip/o.tif`` →
    ``("/d/a.zip", "o.tif")``; the archive is the longest leading part that is a file); ``None`` for other paths,
    archives on remote file systems, or when no leading part is a file.
    """
    prefix = next((p for p in ARCHIVE_VSI if path.startswith(p)), None)
    if prefix is None:
        return None
    rest = path[len(prefix):]
    if rest.startswith("{") and "}" in rest:
        inner, member = rest[1:rest.index("}")], rest[rest.index("}") + 1:].lstrip("/")
        return (inner, member) if os.path.isfile(inner) else None
    if rest.startswith("/vsi"):
        return None
    parts = rest.split("/")
    for k in range(len(parts), 0, -1):
        candidate = "/".join(parts[:k])
        if candidate and os.path.isfile(candidate):
            return candidate, "/".join(parts[k:])
    return None


def local_archive(path: str) -> str | None:
    """The local archive file of a ``/vsizip/``-like path (:func:`archive_parts`), if any."""
    parts = archive_parts(path)
    return None if parts is None else parts[0]


#: Seconds :func:`probe_url` waits for a server (``GDAL_HTTP_TIMEOUT`` when it is shorter).
PROBE_TIMEOUT = 15.0


def probe_url(path: str) -> str | None:
    """Why an HTTP(S) raster (a URL or ``/vsicurl/`` path) cannot be read, in the server's terms: ``"the server at
    HOST did not answer within N s"``, ``"HTTP 403 Forbidden"``, ...; ``None`` when it answers normally or the
    path is not HTTP(S). One ``HEAD`` request; for a message after GDAL could not open the file.
    """
    import urllib.error
    import urllib.request

    url = path[len("/vsicurl/"):] if path.startswith("/vsicurl/") else path
    if not url.lower().startswith(("http://", "https://")):
        return None
    try:
        timeout = min(PROBE_TIMEOUT, float(os.environ.get("GDAL_HTTP_TIMEOUT", PROBE_TIMEOUT)))
    except ValueError:
        timeout = PROBE_TIMEOUT
    try:
        with urllib.request.urlopen(urllib.request.Request(url, method="HEAD"), timeout=timeout):  # noqa: S310
            return None
    except urllib.error.HTTPError as exc:
        return f"HTTP {exc.code} {exc.reason}"
    except TimeoutError:
        return (f"the server did not answer within {timeout:g} s (a hung server or a very slow link; "
                "GDAL_HTTP_TIMEOUT sets how long to wait)")
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        if isinstance(reason, TimeoutError):
            return f"the server did not answer within {timeout:g} s (GDAL_HTTP_TIMEOUT sets how long to wait)"
        return f"the server cannot be reached: {reason}"


#: No directory listing when a remote file is opened (one request instead of a listing of the whole prefix and
#: probes for sidecar files): set around the remote open only (:func:`aerialmtl.io.align.open_raster`), never in
#: the environment, where it would hide a later local file's world file or .aux.xml in the same process.
REMOTE_OPEN_OPTIONS: dict[str, str] = {"GDAL_DISABLE_READDIR_ON_OPEN": "EMPTY_DIR"}


def configure_remote() -> None:
    """Apply :data:`REMOTE_GDAL_OPTIONS` for this process, keeping any the user set.

    They go into the environment, which GDAL reads for every option no ``rasterio.Env`` sets, so they
    hold in every thread (the window readers run in background threads).
    """
    for key, value in REMOTE_GDAL_OPTIONS.items():
        os.environ.setdefault(key, value)


__all__ = ["ARCHIVE_VSI", "NETWORK_VSI", "PROBE_TIMEOUT", "REMOTE_GDAL_OPTIONS", "REMOTE_OPEN_OPTIONS", "SCHEMES",
           "archive_parts",
           "configure_remote", "gdal_path", "is_local", "is_remote", "local_archive", "probe_url", "raster_name",
           "raster_stem", "recorded_path"]
