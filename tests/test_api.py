"""The public API: ``from aerialmtl import ...`` gives the library's own objects, and stays light to import."""

from __future__ import annotations

import importlib
import subprocess
import sys

import aerialmtl


def test_every_public_name_resolves_to_its_defining_object() -> None:
    for name in aerialmtl.__all__:
        if name == "__version__":
            continue
        value = getattr(aerialmtl, name)
        module = importlib.import_module(aerialmtl._EXPORTS[name])
        assert value is getattr(module, name), name
    assert set(aerialmtl.__all__) == {"__version__", *aerialmtl._EXPORTS}
    assert "train" in dir(aerialmtl) and "predict_raster" in dir(aerialmtl)


def test_import_is_light_and_unknown_names_fail_clearly() -> None:
    code = "import sys, aerialmtl; print('torch' in sys.modules, 'rasterio' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]  # the CLI's --help and --version do not pay for torch
    try:
        aerialmtl.no_such_thing  # noqa: B018
    except AttributeError as exc:
        assert "no_such_thing" in str(exc)
    else:  # pragma: no cover
        raise AssertionError("an unknown name must raise AttributeError")
