"""On-disk contracts of aerialmtl, one module per format.

Every reader and writer of a format goes through its module here, so each file name, tag, key and
nodata value is spelled once:

* :mod:`aerialmtl.formats.tiles` — the tile folder (``dataset.yaml``, ``manifest.csv``, the patch cache);
* :mod:`aerialmtl.formats.checkpoint` — the self-describing checkpoint (``best.pt`` / ``last.pt``);
* :mod:`aerialmtl.formats.prediction` — the prediction folder (layer files, tags, nodata, ``prediction.json``).
"""
