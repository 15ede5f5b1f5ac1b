"""The tile folder's replacement: claim ``OUT``, then swap a staged tile dataset into it whole.

:func:`~aerialmtl.tiling.tile.tile_dataset` writes its patches, ``manifest.csv`` and ``dataset.yaml`` into a
staging folder (``OUT/.patches.partial``); this module decides whether ``OUT`` may be written
(:func:`claim`: only an earlier tile dataset's own files are replaced) and swaps the staged set in. The swap
starts by writing a journal (:data:`SWAP_FILE`, the earlier set's files to remove) into the staging folder;
from then on it is rolled forward, by the interrupted run itself or by the next run
(:func:`finish_interrupted_swap`), so ``OUT`` holds either the earlier tile dataset or the new one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

from aerialmtl.errors import OutputError, OutputExistsError
from aerialmtl.filesafety import atomic_write, staging_path
from aerialmtl.formats.tiles import DATASET_YAML, MANIFEST_CSV, STAGING_NAME, TileFolderInfo, owned_files
from aerialmtl.io.outputs import OutputFolder
from aerialmtl.tiling.splits import SPLITS


def claim(folder: OutputFolder, overwrite: bool) -> list[str] | None:
    """Check that a tile dataset may be written into ``folder``; returns the earlier run's own files.

    Raises:
        OutputExistsError: a tile dataset (or part of one) is there and ``overwrite`` is false.
        OutputError: a split folder is there that no tile dataset lists (never replaced).
    """
    names = (*SPLITS, MANIFEST_CSV, DATASET_YAML)
    existing = folder.existing(names)
    if not existing:
        return []
    owned = owned_files(folder.path)
    foreign = [n for n in existing if n in SPLITS] if owned is None else []
    if foreign:
        raise OutputError(
            f"tile folder '{folder.path}' holds {', '.join(foreign)} but no tile dataset (dataset.yaml with its "
            "manifest.csv) lists them, so they were not written by `aerialmtl tile` (or by an unfinished run of an "
            "older version) and are not replaced; move them away or choose another ‹out_dir›")
    if not overwrite:
        raise OutputExistsError(
            f"output folder '{folder.path}' already holds {', '.join(existing)}; choose another ‹out_dir› or pass "
            "‹overwrite=True› to replace the tile dataset")
    return owned or []


def _remove_dataset(out_dir: Path, owned: Sequence[str]) -> None:
    """Remove the files of an earlier tile run (``owned``), dataset.yaml first, then emptied folders."""
    for name in (DATASET_YAML, MANIFEST_CSV):  # first, so a half-replaced folder reads as unfinished
        (out_dir / name).unlink(missing_ok=True)
    parents: set[Path] = set()
    for rel in owned:
        path = out_dir / rel
        path.unlink(missing_ok=True)
        parents.update(p for p in path.parents if p != out_dir and out_dir in p.parents)
    for folder in sorted(parents, key=lambda p: len(p.parts), reverse=True):
        with contextlib.suppress(OSError):
            folder.rmdir()  # only when empty: a user's file inside keeps it


def _move_into(src: Path, dst: Path) -> None:
    """Move ``src`` (a file or folder) to ``dst``, merging into a folder that is already there.

    A file replaces the file of the same name.
    """
    if not dst.exists() or not src.is_dir():
        os.replace(src, dst)
        return
    for child in src.iterdir():
        _move_into(child, dst / child.name)
    src.rmdir()


#: The swap's journal inside the staging folder: written when the staged tile dataset is whole, it lists the
#: earlier set's files to remove (those the new set does not replace); its presence means "roll forward".
SWAP_FILE = "swap.json"


def commit(stage: Path, out_dir: Path, owned: Sequence[str], info: TileFolderInfo) -> None:
    """Swap the staged tile dataset (patches, manifest) and ``info`` (its ``dataset.yaml``) into ``out_dir``.

    It replaces the earlier dataset (``owned``): journal first, then :func:`finish_swap`.
    """
    dataclasses.replace(info, root=stage).write()
    new = {p.relative_to(stage).as_posix() for p in stage.rglob("*") if p.is_file()}
    journal = {"remove": sorted(set(owned) - new)}
    with atomic_write(stage / SWAP_FILE) as tmp:
        tmp.write_text(json.dumps(journal), encoding="utf-8")
    finish_swap(stage, out_dir)


def finish_swap(stage: Path, out_dir: Path) -> None:
    """Carry out (or finish) the swap journaled in ``stage`` (:data:`SWAP_FILE`).

    Every step can be repeated, so an interrupted swap is finished by calling this again.
    """
    plan = json.loads((stage / SWAP_FILE).read_text(encoding="utf-8"))
    if (stage / DATASET_YAML).exists():  # the earlier dataset.yaml first: a half-swapped folder reads unfinished
        (out_dir / DATASET_YAML).unlink(missing_ok=True)
    _remove_dataset(out_dir, [str(f) for f in plan.get("remove", [])])
    for split in SPLITS:
        if (stage / split).exists():
            _move_into(stage / split, out_dir / split)
    for name in (MANIFEST_CSV, DATASET_YAML):  # dataset.yaml last
        if (stage / name).exists():
            os.replace(stage / name, out_dir / name)
    shutil.rmtree(stage)


def finish_interrupted_swap(out_dir: Path) -> bool:
    """Roll forward the swap a killed run left journaled in ``out_dir``; returns whether there was one.

    Call it under the folder's lock.
    """
    stage = staging_path(out_dir / STAGING_NAME)
    if not (stage / SWAP_FILE).is_file():
        return False
    finish_swap(stage, out_dir)
    return True


__all__ = ["SWAP_FILE", "claim", "commit", "finish_interrupted_swap", "finish_swap"]
