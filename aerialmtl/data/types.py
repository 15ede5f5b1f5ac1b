"""The sample dictionary passed between datasets, transforms, the training loop and losses."""

from __future__ import annotations

from typing import Any, TypedDict, cast

import torch


class Sample(TypedDict, total=False):
    """One training patch (a batch adds a leading B dimension to every tensor).

    Keys:
        image: float32 (C, H, W), normalised with the dataset's per-band mean/std.
        height: float32 (1, H, W), metres above ground; 0 where ``height_valid`` is False.
        height_valid: bool (1, H, W), True where the reference height is valid.
        classes: int64 (H, W), class indices 0..K-1, ``IGNORE_INDEX`` (255) where unlabelled.
        patch_id: str, the manifest's patch id.
    """

    image: torch.Tensor
    height: torch.Tensor
    height_valid: torch.Tensor
    classes: torch.Tensor
    patch_id: str


def as_sample(fields: dict[str, Any]) -> Sample:
    """``fields`` as the :class:`Sample` they are (the same dict, not a copy).

    For a sample put together key by key (a batch's split, a transform's output): a TypedDict cannot be built
    from keys known only when the code runs, and this is the one place that says they are a sample's.
    """
    return cast(Sample, fields)
