"""Why a raster cannot be opened or read, in words a user can act on: a FIFO or device GDAL would wait on forever
(:func:`raise_if_blocking`), and a read that failed after the open (:func:`read_error`: GDAL's own words and, for a
URL, what the server answers when asked again).
"""

from __future__ import annotations

from pathlib import Path

from aerialmtl.errors import InputError, cause
from aerialmtl.io.fingerprint import blocking_file
from aerialmtl.io.paths import gdal_path, is_remote, probe_url


def raise_if_blocking(path: str | Path, role: str = "raster") -> None:
    """Refuse local raster ``path`` when it or a sidecar GDAL reads with it is a FIFO, a socket or a device
    (:func:`~aerialmtl.io.fingerprint.blocking_file`): GDAL would wait on it forever.

    Raises:
        InputError: naming the file, what it is, and the fix.
    """
    found = blocking_file(path)
    if found is None:
        return
    bad, kind = found
    what = "it" if bad == Path(path) else f"'{bad}', which GDAL reads with it,"
    raise InputError(f"{role} '{path}' cannot be opened: {what} is {kind}, not a regular file (GDAL would wait on it "
                     f"forever); remove '{bad}' or replace it with the file it should be")


def gdal_message(exc: BaseException) -> str:
    """GDAL's own words for a failed read, in whole sentences.

    rasterio chains the CPLE error as the cause, and says only "Read failed. See previous exception for details."
    itself.
    """
    seen: BaseException | None = exc
    while seen is not None:
        text = " ".join(str(seen).split())
        if text and "See previous exception" not in text:
            return cause(text)
        seen = seen.__cause__ or seen.__context__
    return "read failed"


def read_error(role: str, path: str | Path, exc: BaseException) -> InputError:
    """The error to raise when reading pixels of an opened raster failed (``exc``).

    It names the path or URL, what failed
    (GDAL's words and, for a URL, what the server answers when asked again: an HTTP status, a refused or closed
    connection, a timeout) and the fix.
    """
    gpath = gdal_path(path)
    why = gdal_message(exc)
    if is_remote(gpath):
        server = probe_url(gpath)
        now = (f"asked again, the server answers: {server}" if server else
               "asked again, the server answers normally: the connection was dropped or timed out in between")
        url = gpath[len("/vsicurl/"):] if gpath.startswith("/vsicurl/") else gpath
        return InputError(
            f"{role} '{url}' could not be read after it was opened (GDAL: {why}; {now}); check the network and the "
            "server, then re-run (GDAL_HTTP_TIMEOUT and GDAL_HTTP_MAX_RETRY set how long and how often it retries)")
    if str(path).lower().endswith(".vrt") and "No such file" in why:
        return InputError(f"{role} '{path}' could not be read: a source file it lists is missing ({why}); restore "
                          "it, or rebuild the VRT over the files you have (`gdalbuildvrt`)")
    return InputError(f"{role} '{path}' could not be read ({why}); the file is probably truncated or corrupt: check "
                      f"it with `gdalinfo -checksum {path}`, then re-download or re-export it")


__all__ = ["gdal_message", "raise_if_blocking", "read_error"]
