"""Land-cover class schemes: raw raster codes → contiguous class indices, with names and colours.

A scheme is a YAML file::

    name: synthetic
    ignore_codes: [0]          # raw codes meaning "no label" (→ IGNORE_INDEX)
    classes:                   # index = position in this list
      - {code: 1, name: bare soil, color: [180, 150, 110]}
      - {code: 2, name: road, color: [90, 90, 90]}

Remapped label arrays are ``uint8`` with :data:`IGNORE_INDEX` (255) wherever the pixel has no usable
label (an ignore code, nodata, or — when asked — an unknown code).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from aerialmtl.config import from_dict, read_yaml, to_dict
from aerialmtl.errors import ConfigError, LabelError

#: Class index written for "no label" in patches, predictions and losses (cross-entropy ignore_index).
IGNORE_INDEX = 255
#: What :meth:`ClassScheme.remap` does with a code that is neither a class nor an ignore code.
OnUnknown = Literal["error", "ignore"]

#: Folder of the class schemes shipped with the package (``dfc2018``, ``isprs``, ``synthetic``).
BUILTIN_DIR = Path(__file__).resolve().parent / "resources" / "classes"


@dataclass(frozen=True)
class ClassDef:
    """One class: the raw ``code`` in label rasters, a display ``name`` and an RGB ``color`` (0–255)."""

    code: int
    name: str
    color: tuple[int, int, int] = (128, 128, 128)

    def __post_init__(self) -> None:
        if any(not 0 <= c <= 255 for c in self.color):
            raise ConfigError(f"class '{self.name}': color {list(self.color)} must be 3 integers in 0..255")


@dataclass(frozen=True)
class ClassScheme:
    """An ordered list of classes (index = position) plus raw codes to ignore."""

    name: str
    classes: tuple[ClassDef, ...]
    ignore_codes: tuple[int, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        if not self.classes:
            raise ConfigError(f"class scheme '{self.name}': 'classes' is empty; list at least one class")
        if len(self.classes) >= IGNORE_INDEX:
            raise ConfigError(f"class scheme '{self.name}': at most {IGNORE_INDEX - 1} classes are supported")
        codes = [c.code for c in self.classes]
        dup = sorted({c for c in codes if codes.count(c) > 1})
        if dup:
            raise ConfigError(f"class scheme '{self.name}': codes {dup} are listed more than once")
        both = sorted(set(codes) & set(self.ignore_codes))
        if both:
            raise ConfigError(f"class scheme '{self.name}': codes {both} are both classes and ignore_codes")

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ClassScheme:
        """Build from a plain mapping (as in the YAML file or a checkpoint)."""
        return from_dict(cls, data)

    @classmethod
    def load(cls, path: str | Path) -> ClassScheme:
        """Load a scheme from a YAML file, or a built-in one by name (``dfc2018``, ``isprs``, ``synthetic``)."""
        p = Path(path)
        if not p.exists() and (BUILTIN_DIR / f"{path}.yaml").is_file():
            p = BUILTIN_DIR / f"{path}.yaml"
        if not p.is_file():
            builtin = ", ".join(sorted(q.stem for q in BUILTIN_DIR.glob("*.yaml")))
            raise ConfigError(f"class scheme '{path}' not found; pass a YAML file or one of: {builtin}")
        try:
            return cls.from_dict(read_yaml(p))
        except ConfigError as exc:
            raise ConfigError(f"{p}: {exc}") from exc

    def to_dict(self) -> dict[str, Any]:
        """Plain mapping (YAML/JSON/checkpoint safe)."""
        result: dict[str, Any] = to_dict(self)
        return result

    # ---- accessors ----------------------------------------------------------------------------
    @property
    def num_classes(self) -> int:
        """Number of classes K (the model's class channels)."""
        return len(self.classes)

    @property
    def names(self) -> list[str]:
        """Class names, in class-index order."""
        return [c.name for c in self.classes]

    @property
    def colors(self) -> list[tuple[int, int, int]]:
        """RGB colours (0–255) of the classes, in class-index order."""
        return [(*c.color,) for c in self.classes]

    @property
    def codes(self) -> list[int]:
        """Raw label codes of the classes, in class-index order."""
        return [c.code for c in self.classes]

    def colormap(self) -> dict[int, tuple[int, int, int, int]]:
        """GDAL colour table for index rasters: index → RGBA, ``IGNORE_INDEX`` transparent black."""
        cmap = {i: (*c.color, 255) for i, c in enumerate(self.classes)}
        cmap[IGNORE_INDEX] = (0, 0, 0, 0)
        return cmap

    # ---- remapping ----------------------------------------------------------------------------
    def remap(
        self,
        codes: np.ndarray,
        valid: np.ndarray | None = None,
        on_unknown: OnUnknown = "error",
        source: str = "labels",
    ) -> np.ndarray:
        """Raw label codes → class indices.

        Args:
            codes: integer array (any shape) of raw codes.
            valid: optional bool array of the same shape; ``False`` pixels (nodata) → ``IGNORE_INDEX``.
            on_unknown: ``"error"`` raises on codes that are neither classes nor ignore codes;
                ``"ignore"`` maps them to ``IGNORE_INDEX``.
            source: name of the file, for messages.

        Returns:
            ``uint8`` array of the same shape with indices ``0..K-1`` or ``IGNORE_INDEX``.

        Raises:
            LabelError: unknown codes with ``on_unknown="error"``; lists them and the fix.
        """
        codes = np.asarray(codes)
        if codes.dtype.kind == "f":
            finite = np.isfinite(codes)
            valid = finite if valid is None else (valid & finite)
            codes = np.where(finite, codes, 0).astype(np.int64)
        known = np.array(self.codes, dtype=np.int64)
        order = np.argsort(known)
        sorted_codes = known[order]
        pos = np.clip(np.searchsorted(sorted_codes, codes), 0, len(sorted_codes) - 1)
        hit = sorted_codes[pos] == codes
        out = np.where(hit, order[pos], IGNORE_INDEX).astype(np.uint8)
        considered = np.ones(codes.shape, bool) if valid is None else np.asarray(valid, bool)
        if self.ignore_codes:
            considered &= ~np.isin(codes, np.array(self.ignore_codes, dtype=np.int64))
        if on_unknown == "error":
            bad = considered & ~hit
            if bad.any():
                unknown = np.unique(codes[bad])
                shown = ", ".join(str(int(u)) for u in unknown[:20]) + (" ..." if unknown.size > 20 else "")
                raise LabelError(
                    f"{source}: label codes {shown} are not in class scheme '{self.name}' "
                    f"(known codes: {self.codes}, ignored: {list(self.ignore_codes)}); add them to the "
                    f"scheme's 'classes' or 'ignore_codes', or pass ‹ignore_unknown_codes=True› to treat them as "
                    "no label"
                )
        out[~considered] = IGNORE_INDEX
        return out
