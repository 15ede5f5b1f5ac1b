"""Everything the trainer needs to run as several processes (``torchrun``), in one place.

``torchrun --nproc_per_node N -m aerialmtl train ...`` starts N processes with ``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT`` set; :meth:`DistContext.from_env` turns them into a
process group (through :class:`aerialmtl.runtime.Torchrun`, which prediction uses too): ``nccl`` with one GPU
per process (``cuda:LOCAL_RANK``) when training on CUDA, ``gloo`` with one CPU process each otherwise. Without
``WORLD_SIZE`` (a plain ``aerialmtl train``) the context is a single process and every method here is a no-op,
so the trainer has no ``if distributed`` branches.

What each part does with several processes:

* data: each rank gets a disjoint share of every global batch (see :class:`~aerialmtl.data.batches.EpochPlan`);
  ``data.batch_size`` is per process, the global batch is ``batch_size × world_size``;
* gradients: :func:`wrap` puts the model (and the learned task weighting) in
  ``DistributedDataParallel``, which averages gradients over ranks;
* BatchNorm: with ``model.sync_bn`` the statistics are computed over the global batch
  (:func:`convert_sync_batchnorm`; torch's ``SyncBatchNorm`` on GPUs, :class:`CpuSyncBatchNorm` on CPUs,
  where torch's refuses to run);
* validation and logged losses: sums reduced over ranks (:meth:`DistContext.all_reduce_sum`);
* files: rank 0 alone writes checkpoints, the log and the config (:attr:`DistContext.is_main`).

When a process dies, its peers' next collective fails (gloo/nccl see the closed connection) and
``torchrun`` stops the rest; :func:`peer_failure_message` words what the survivors report.
Checkpoints are written atomically by rank 0, so the last one stays whole.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import torch
import torch.distributed as dist
from torch import nn

from aerialmtl import runtime
from aerialmtl.errors import AerialMTLError, ConfigError

T = TypeVar("T")

#: How long a collective may wait for a peer (:data:`aerialmtl.runtime.COLLECTIVE_TIMEOUT`).
TIMEOUT = runtime.COLLECTIVE_TIMEOUT


class PeerFailure(AerialMTLError, RuntimeError):
    """Another process of a multi-process run failed or was stopped."""


def resolve_device(name: str, local_rank: int = 0) -> torch.device:
    """``auto`` → CUDA when available, else CPU; ``cuda`` without a GPU is an error
    (:func:`aerialmtl.runtime.resolve_device`, raising :class:`ConfigError`).

    With several processes on CUDA each gets ``cuda:local_rank``.
    """
    return runtime.resolve_device(name, local_rank, ConfigError)


@dataclass
class DistContext:
    """Rank, world size and device of this process; collectives that are no-ops for one process.

    Attributes:
        device: the training device of this process.
        rank: global rank (0 for one process).
        world_size: number of processes.
        local_rank: rank on this machine (selects the GPU).
        owns_group: whether :meth:`close` destroys the process group (it created it).
    """

    device: torch.device
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    owns_group: bool = False

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that writes files and prints."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @classmethod
    def from_env(cls, device: str = "auto") -> DistContext:
        """A context from torchrun's environment variables (one process without them).

        Args:
            device: ``auto``, ``cpu`` or ``cuda`` (the config's ``device``).

        Raises:
            ConfigError: ``cuda`` without a GPU, or more processes on this machine than GPUs.
        """
        env = runtime.Torchrun.from_env()
        dev = env.device(device, ConfigError)
        owns = env.join(dev, TIMEOUT)
        return cls(device=dev, rank=env.rank, world_size=env.world, local_rank=env.local_rank, owns_group=owns)

    def close(self) -> None:
        """Destroy the process group if this context created it."""
        if self.owns_group and dist.is_initialized():
            dist.destroy_process_group()
            self.owns_group = False

    # ---- collectives (no-ops for one process) -------------------------------------------------------
    def barrier(self) -> None:
        if self.distributed:
            _collective(dist.barrier)

    def all_reduce_sum(self, tensor: torch.Tensor) -> torch.Tensor:
        """Sum ``tensor`` over ranks, in place (identical on every rank afterwards); returns it.

        A CPU tensor in a CUDA (nccl) run travels through the GPU and comes back.
        """
        if self.distributed:
            comm = self._comm_device()
            work = tensor if tensor.device == comm else tensor.to(comm)
            _collective(dist.all_reduce, work, op=dist.ReduceOp.SUM)
            if work is not tensor:
                tensor.copy_(work)
        return tensor

    def any(self, flag: bool) -> bool:
        """True on every rank when ``flag`` is true on at least one."""
        if not self.distributed:
            return flag
        t = torch.tensor([1.0 if flag else 0.0], device=self._comm_device())
        return bool(self.all_reduce_sum(t).item() > 0)

    def gather_objects(self, obj: Any) -> list[Any]:
        """``obj`` of every rank, in rank order (on every rank)."""
        if not self.distributed:
            return [obj]
        out: list[Any] = [None] * self.world_size
        _collective(dist.all_gather_object, out, obj)
        return out

    def broadcast_object(self, obj: T) -> T:
        """Rank 0's ``obj`` on every rank."""
        if not self.distributed:
            return obj
        box = [obj]
        _collective(dist.broadcast_object_list, box, src=0)
        return box[0]

    def main_first(self, fn: Callable[[], T]) -> T:
        """Run ``fn`` on rank 0; if it raises, every rank raises the same error (no rank is left waiting)."""
        result: Any = None
        error: BaseException | None = None
        if self.is_main:
            try:
                result = fn()
            except (AerialMTLError, OSError) as exc:
                error = exc
        error = self.broadcast_object(error)
        if error is not None:
            raise error
        return result

    def _comm_device(self) -> torch.device:
        return self.device if self.device.type == "cuda" else torch.device("cpu")


def peer_failure_message(exc: BaseException) -> str:
    why = " ".join(str(exc).split())[:160] or exc.__class__.__name__
    return (f"another process of this multi-process run failed or was stopped ({why}); its own message or "
            "torchrun's summary says why. The last checkpoint in the run folder is whole: continue with ‹resume=True›")


def is_peer_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a collective failing because another process is gone (gloo/nccl wording)."""
    if isinstance(exc, (dist.DistBackendError, dist.DistNetworkError)):
        return True
    text = str(exc)
    return isinstance(exc, RuntimeError) and any(
        s in text for s in ("Connection reset", "Connection closed", "Broken pipe", "gloo", "NCCL", "by peer"))


def _collective(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Call a torch.distributed collective; a broken peer becomes :class:`PeerFailure`."""
    try:
        return fn(*args, **kwargs)
    except RuntimeError as exc:
        if is_peer_error(exc):
            raise PeerFailure(peer_failure_message(exc)) from exc
        raise


def install_stop_handler() -> None:
    """Turn SIGTERM (what torchrun sends the survivors when a process dies) into :class:`PeerFailure`.

    The process then unwinds normally: temporary checkpoint files are removed and the rank says why it
    stopped, instead of vanishing mid-write. SIGHUP stays Ctrl-C-like (:mod:`aerialmtl.signals`, the one
    place stop signals are handled).
    """
    from aerialmtl.signals import install_stop_signals

    install_stop_signals(distributed=True,
                         on_peer_stop=lambda: PeerFailure(peer_failure_message(RuntimeError("torchrun sent SIGTERM"))))


# ---- models -------------------------------------------------------------------------------------
def all_reduce(tensor: torch.Tensor) -> torch.Tensor:
    """Differentiable sum over ranks (the gradient of each input is the sum of the output gradients)."""
    from torch.distributed import _functional_collectives as fc

    world = dist.group.WORLD
    assert world is not None
    if hasattr(fc, "all_reduce_backward"):  # functional collectives with autograd (recent torch)
        return fc.wait_tensor(fc.all_reduce(tensor, "sum", world))
    from torch.distributed.nn.functional import all_reduce as legacy  # pragma: no cover - older torch

    return legacy(tensor)  # pragma: no cover


class CpuSyncBatchNorm(nn.BatchNorm2d):
    """BatchNorm2d whose training statistics are taken over the batches of every rank, on any device.

    torch's ``nn.SyncBatchNorm`` only runs on GPUs; this one uses differentiable all-reduces
    (``torch.distributed.nn``), so it works with gloo on CPUs. Per channel: the mean over every rank's
    pixels, then the biased variance around it (two passes, as accurate as a single process), normalise;
    running statistics get the unbiased variance, like ``BatchNorm2d``. Outside training, or with one
    process, it is a plain ``BatchNorm2d``. State-dict keys are those of ``BatchNorm2d``.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
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
        return nn.SyncBatchNorm.convert_sync_batchnorm(model)
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


def wrap(module: nn.Module, ctx: DistContext) -> nn.Module:
    """``module`` in ``DistributedDataParallel`` with several processes; unchanged with one."""
    if not ctx.distributed:
        return module
    from torch.nn.parallel import DistributedDataParallel

    ids = [ctx.device.index] if ctx.device.type == "cuda" else None
    return DistributedDataParallel(module, device_ids=ids)


__all__ = ["DistContext", "PeerFailure", "resolve_device", "convert_sync_batchnorm", "CpuSyncBatchNorm", "wrap",
           "install_stop_handler", "peer_failure_message", "is_peer_error", "all_reduce", "TIMEOUT"]
