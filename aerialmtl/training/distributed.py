"""Everything the trainer needs to run as several processes (``torchrun``), in one place.

``torchrun --nproc_per_node N -m aerialmtl train ...`` starts N processes with ``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT`` set; :meth:`aerialmtl.runtime.Torchrun.start` (the one
process context, which prediction uses too) turns them into a process group: ``nccl`` with one GPU
per process (``cuda:LOCAL_RANK``) when training on CUDA, ``gloo`` with one CPU process each otherwise. Without
``WORLD_SIZE`` (a plain ``aerialmtl train``) the context is a single process and every method here is a no-op,
so the trainer has no ``if distributed`` branches.

What each part does with several processes:

* data: each rank gets a disjoint share of every global batch (see :class:`~aerialmtl.data.batches.EpochOrder`);
  ``data.batch_size`` is per process, the global batch is ``batch_size × world_size``;
* gradients: :func:`wrap` puts the model (and the learned task weighting) in
  ``DistributedDataParallel``, which averages gradients over ranks;
* BatchNorm: with ``model.sync_bn`` the statistics are computed over the global batch
  (:func:`convert_sync_batchnorm`; torch's ``SyncBatchNorm`` on GPUs, :class:`CpuSyncBatchNorm` on CPUs,
  where torch's refuses to run);
* validation and logged losses: sums reduced over ranks (:meth:`~aerialmtl.runtime.Torchrun.all_reduce_sum`);
* files: rank 0 alone writes checkpoints, the log and the config (:attr:`~aerialmtl.runtime.Torchrun.is_main`).

When a process dies, its peers' next collective fails (gloo/nccl see the closed connection) and
``torchrun`` stops the rest; :func:`aerialmtl.runtime.peer_failure` words what the survivors report.
Checkpoints are written atomically by rank 0, so the last one stays whole.
"""

from __future__ import annotations

import torch
import torch.distributed as dist
from torch import nn

from aerialmtl.runtime import Torchrun, peer_failure
from aerialmtl.signals import install_stop_signals


def install_stop_handler() -> None:
    """Turn SIGTERM (what torchrun sends the survivors when a process dies) into a
    :class:`~aerialmtl.errors.PeerFailure`.

    The process then unwinds normally: temporary checkpoint files are removed and the rank says why it
    stopped, instead of vanishing mid-write. SIGHUP stays Ctrl-C-like (:mod:`aerialmtl.signals`, the one
    place stop signals are handled).
    """
    install_stop_signals(distributed=True, on_peer_stop=lambda: peer_failure(RuntimeError("torchrun sent SIGTERM")))


# ---- models -------------------------------------------------------------------------------------
def all_reduce(tensor: torch.Tensor) -> torch.Tensor:
    """Differentiable sum over ranks (the gradient of each input is the sum of the output gradients)."""
    from torch.distributed import _functional_collectives as fc

    world = dist.group.WORLD
    assert world is not None
    if hasattr(fc, "all_reduce_backward"):  # functional collectives with autograd (recent torch)
        result: torch.Tensor = fc.wait_tensor(fc.all_reduce(tensor, "sum", world))
        return result
    from torch.distributed.nn.functional import all_reduce as legacy  # pragma: no cover - older torch

    reduced: torch.Tensor = legacy(tensor)  # pragma: no cover
    return reduced


class CpuSyncBatchNorm(nn.BatchNorm2d):
    """BatchNorm2d whose training statistics are taken over the batches of every rank, on any device.

    torch's ``nn.SyncBatchNorm`` only runs on GPUs; this one uses differentiable all-reduces
    (``torch.distributed.nn``), so it works with gloo on CPUs. Per channel: the mean over every rank's
    pixels, then the biased variance around it (two passes, as accurate as a single process), normalise;
    running statistics get the unbiased variance, like ``BatchNorm2d``. Outside training, or with one
    process, it is a plain ``BatchNorm2d``. State-dict keys are those of ``BatchNorm2d``.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Normalise ``x`` (N, C, H, W) with statistics over every rank's batch while training."""
        if not (self.training and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(x)
        xf = x.float()
        count = torch.tensor([xf.numel() // xf.shape[1]], dtype=torch.float32, device=x.device)
        stats = all_reduce(torch.cat([xf.sum(dim=(0, 2, 3)), count]))
        n = stats[-1]
        mean = stats[:-1] / n
        centred = xf - mean.view(1, -1, 1, 1)
        var = all_reduce((centred * centred).sum(dim=(0, 2, 3))) / n
        y = centred * torch.rsqrt(var + self.eps).view(1, -1, 1, 1)
        if self.affine:
            y = y * self.weight.view(1, -1, 1, 1) + self.bias.view(1, -1, 1, 1)
        if self.track_running_stats and self.running_mean is not None and self.running_var is not None:
            with torch.no_grad():
                tracked = self.num_batches_tracked
                assert tracked is not None
                tracked.add_(1)
                m = 1.0 / float(tracked) if self.momentum is None else self.momentum
                self.running_mean.mul_(1 - m).add_(mean.detach(), alpha=m)
                self.running_var.mul_(1 - m).add_(var.detach() * n / (n - 1).clamp(min=1), alpha=m)
        return y


def convert_sync_batchnorm(model: nn.Module, device: torch.device) -> nn.Module:
    """Replace every BatchNorm2d of ``model`` by a synchronised one (weights and statistics kept)."""
    if device.type == "cuda":
        result: nn.Module = nn.SyncBatchNorm.convert_sync_batchnorm(model)
        return result
    for name, child in list(model.named_children()):
        if isinstance(child, nn.BatchNorm2d) and not isinstance(child, CpuSyncBatchNorm):
            new = CpuSyncBatchNorm(child.num_features, child.eps, child.momentum, child.affine,
                                   child.track_running_stats)
            new.load_state_dict(child.state_dict())
            new.train(child.training)
            setattr(model, name, new.to(device))
        else:
            convert_sync_batchnorm(child, device)
    return model


def wrap(module: nn.Module, ctx: Torchrun) -> nn.Module:
    """``module`` in ``DistributedDataParallel`` with several processes; unchanged with one."""
    if not ctx.distributed:
        return module
    from torch.nn.parallel import DistributedDataParallel

    ids = [ctx.device.index] if ctx.device.type == "cuda" else None
    return DistributedDataParallel(module, device_ids=ids)


__all__ = ["CpuSyncBatchNorm", "all_reduce", "convert_sync_batchnorm", "install_stop_handler", "wrap"]
