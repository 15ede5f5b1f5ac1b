"""The OpenVINO engine's requests in flight.

Infer requests used in turn, the jobs started on them, and the reused output buffers of T = 1 windows.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from aerialmtl import runtime
from aerialmtl.inference.engines.openvino_graphs import _as_planes
from aerialmtl.models.mc_dropout import McStatistics, single_pass_statistics


class _Job:
    """One inference started on a request of :class:`_Requests`; :meth:`outputs` waits for it (once).

    With ``direct``, the request writes its outputs straight into ``dest`` (set as its output tensors): nothing
    is copied when it is collected.
    """

    def __init__(self, owner: _Requests | None = None, slot: int = 0, dest: list[np.ndarray] | None = None,
                 direct: bool = False) -> None:
        self.owner, self.slot, self.dest, self.direct = owner, slot, dest, direct
        self._outputs: list[np.ndarray] | None = None

    def collect(self) -> None:
        """Wait for the request and copy its outputs out, freeing the request.

        Into ``dest`` when given, unless the request wrote there itself.
        """
        if self._outputs is not None or self.owner is None:
            return
        req = self.owner.requests[self.slot]
        req.wait()
        if self.direct:
            assert self.dest is not None
            self._outputs = self.dest
        else:
            tensors = [req.get_output_tensor(k).data for k in range(len(req.model_outputs))]
            if self.dest is not None:
                for d, t in zip(self.dest, tensors):
                    np.copyto(d, t)
                self._outputs = self.dest
            else:
                self._outputs = [np.array(t, copy=True) for t in tensors]
        self.owner.running[self.slot] = None

    def outputs(self) -> list[np.ndarray]:
        """The model's outputs, in order (float32 numpy)."""
        self.collect()
        assert self._outputs is not None
        return self._outputs


_DONE = _Job()


class _Requests:
    """The infer requests of one compiled model, one per stream, used in turn.

    A new job takes the next request, first collecting the job still on it (the oldest, as jobs take similar
    times).
    """

    def __init__(self, compiled: Any, n: int, keep: np.ndarray | None = None) -> None:
        ov = runtime.import_openvino()
        #: The bytes ``compiled`` was imported from: OpenVINO reads them while it runs (:meth:`OpenVINOEngine._import`).
        self.keep = keep
        self._tensor = ov.Tensor
        self.requests = [compiled.create_infer_request() for _ in range(max(1, n))]
        #: The outputs' shapes (one image).
        self.shapes = [tuple(o.get_shape()) for o in compiled.outputs]
        self.running: list[_Job | None] = [None] * len(self.requests)
        # each request's own output tensors, put back when a job without ``dest`` follows one that wrote into
        # the caller's arrays (which the caller may be reading by then)
        self._own = [[req.get_output_tensor(k) for k in range(len(self.shapes))] for req in self.requests]
        self._lent = [False] * len(self.requests)
        self._next = 0

    def start(self, inputs: dict[int, np.ndarray], dest: list[np.ndarray] | None = None) -> _Job:
        """Start one inference on ``inputs`` (copied into the request) and return its job.

        With ``dest`` (one float32 array per output, of its shape), the outputs end up there: written by the
        request itself when the arrays are C-contiguous (no copy), else copied when the job is collected.
        """
        slot = self._next
        self._next = (slot + 1) % len(self.requests)
        busy = self.running[slot]
        if busy is not None:
            busy.collect()
        req = self.requests[slot]
        direct = dest is not None and all(
            d.dtype == np.float32 and d.flags.c_contiguous and d.flags.writeable and tuple(d.shape) == s
            for d, s in zip(dest, self.shapes))
        if direct:
            assert dest is not None
            for k, d in enumerate(dest):
                req.set_output_tensor(k, self._tensor(d, shared_memory=True))
            self._lent[slot] = True
        elif self._lent[slot]:
            for k, t in enumerate(self._own[slot]):
                req.set_output_tensor(k, t)
            self._lent[slot] = False
        job = _Job(self, slot, dest, direct)
        self.running[slot] = job
        req.start_async(inputs)
        return job



class _Forward1:
    """The T = 1 statistics of a batch whose forward passes are running (one job per window).

    The output buffers go back to ``pool`` once the statistics are made from them.
    """

    def __init__(self, tasks: tuple[str, ...], jobs: list[_Job], pool: _BufferPool,
                 unfamiliarity: torch.Tensor | None = None) -> None:
        self.tasks, self.jobs, self.pool, self.unfamiliarity = tasks, jobs, pool, unfamiliarity

    def result(self) -> McStatistics:
        outs = [job.outputs() for job in self.jobs]
        raw = {task: _as_planes(task, torch.cat([torch.from_numpy(o[k]) for o in outs]) if len(outs) > 1
                                else torch.from_numpy(outs[0][k])) for k, task in enumerate(self.tasks)}
        stats = single_pass_statistics(raw)
        if stats.height_mean is not None:  # a view of the buffer, which goes back to the pool
            stats.height_mean = stats.height_mean.clone()
        for o in outs:
            self.pool.give(o)
        stats.unfamiliarity = self.unfamiliarity  # computed from the encoder graph when the batch was submitted
        return stats


class _BufferPool:
    """Output buffers of T = 1 windows, reused.

    A fresh 80 MiB array per window (1024², 20 classes) costs its page faults every time. Holds at most
    ``limit`` sets, of any shapes.
    """

    def __init__(self, limit: int = 4) -> None:
        self.limit = limit
        self.free: list[list[np.ndarray]] = []

    def take(self, shapes: Sequence[tuple[int, ...]]) -> list[np.ndarray]:
        """A set of float32 arrays of ``shapes`` (reused when one is free)."""
        want = [tuple(s) for s in shapes]
        for k, bufs in enumerate(self.free):
            if [b.shape for b in bufs] == want:
                return self.free.pop(k)
        return [np.empty(s, np.float32) for s in want]

    def give(self, bufs: list[np.ndarray]) -> None:
        """Return a set once nothing reads it any more (the oldest free set is dropped beyond ``limit``)."""
        self.free.append(bufs)
        if len(self.free) > self.limit:
            self.free.pop(0)


