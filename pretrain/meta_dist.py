"""Distributed meta-training with ``torch.distributed`` (gloo on CPU, NCCL on GPU), started by ``torchrun``.

Each process works on slots ``rank, rank + world_size, ...`` of every meta-batch and sums their
meta-gradients; one all-reduce adds the sums of all processes, and every process divides by the
meta-batch size and takes the same outer step, so the parameters stay identical everywhere and
equal those of a one-process run over the same tasks (up to the order of the float additions).
Only rank 0 reads or writes the run folder's outputs; decisions it takes alone (a refused
folder, a bad checkpoint) are broadcast so every process stops with the same one-line error.
"""

from __future__ import annotations

import importlib
import os
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Iterator, TypeVar

import torch
import torch.distributed as dist

from nerfmeta.errors import ConfigError, NerfmetaError

T = TypeVar("T")


@dataclass(frozen=True)
class DistContext:
    """Where this process stands in a (possibly one-process) run.

    Attributes:
        rank: this process's index in ``0 .. world_size - 1``.
        world_size: number of processes.
        local_rank: index on this machine (picks the GPU).
        backend: ``gloo`` or ``nccl`` when a process group is initialised, else None.
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.backend is not None and self.world_size > 1

    def device(self, requested: str) -> torch.device:
        """``requested`` for one process; under torchrun, ``cuda`` (or ``cuda:N``) becomes ``cuda:LOCAL_RANK``."""
        device = torch.device(requested)
        if device.type == "cuda" and self.distributed:
            return torch.device("cuda", self.local_rank)
        return device

    def all_reduce_sum_(self, tensor: torch.Tensor) -> torch.Tensor:
        """Sum ``tensor`` over all processes, in place (a no-op for one process)."""
        if self.distributed:
            dist.all_reduce(tensor, op=dist.ReduceOp.SUM)
        return tensor

    def broadcast_object(self, obj: Any) -> Any:
        """Rank 0's ``obj`` on every process (picklable, small: a status, a number)."""
        if not self.distributed:
            return obj
        box = [obj]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    def on_main(self, fn: Callable[[], T]) -> T | None:
        """Run ``fn`` on rank 0 only; if it raises, every process raises (so none waits forever).

        Rank 0 re-raises its own exception; the others raise :class:`ConfigError` with the same
        line for a :class:`NerfmetaError`, else a ``RuntimeError`` naming rank 0's failure.
        Returns ``fn()``'s result on rank 0 and None elsewhere.
        """
        result, status = None, None
        if self.is_main:
            try:
                result = fn()
            except NerfmetaError as err:
                self.broadcast_object(("user", str(err)))
                raise
            except BaseException as err:
                self.broadcast_object(("crash", f"rank 0 failed: {type(err).__name__}: {err}"))
                raise
        status = self.broadcast_object(status)
        if status is not None:
            kind, text = status
            raise ConfigError(text) if kind == "user" else RuntimeError(text)
        return result

    def barrier(self) -> None:
        if self.distributed:
            dist.barrier()


SINGLE = DistContext()
"""The context of an ordinary one-process run."""


def env_world() -> tuple[int, int, int] | None:
    """``(rank, world_size, local_rank)`` from the variables torchrun sets, or None outside torchrun."""
    if "WORLD_SIZE" not in os.environ or "RANK" not in os.environ:
        return None
    try:
        rank, world = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
        local = int(os.environ.get("LOCAL_RANK", rank))
    except ValueError as err:
        raise ConfigError(f"RANK/WORLD_SIZE/LOCAL_RANK are not integers ({err}); start with torchrun") from None
    if not 0 <= rank < world:
        raise ConfigError(f"RANK={rank} is not in 0..WORLD_SIZE-1={world - 1}")
    return rank, world, local


@contextmanager
def distributed_from_env(device: str) -> Iterator[DistContext]:
    """A process group for this process when started by torchrun (gloo for CPU, NCCL for CUDA).

    Outside torchrun, or with ``WORLD_SIZE=1``, yields :data:`SINGLE` and initialises nothing.
    The group is destroyed on exit.
    """
    world = env_world()
    if world is None or world[1] == 1:
        yield SINGLE
        return
    rank, world_size, local_rank = world
    cuda = torch.device(device).type == "cuda"
    if cuda:
        if not torch.cuda.is_available():
            raise ConfigError(f"--device {device}: CUDA is not available on this machine")
        torch.cuda.set_device(local_rank)
    backend = "nccl" if cuda else "gloo"
    # The first optimizer built imports torch._dynamo, and modules it pulls in keep references to
    # the default group when they are imported after it exists (torch 2.13: ten more references,
    # counted with sys.getrefcount). The group then outlives destroy_process_group(), its gloo
    # threads are torn down during interpreter shutdown, and that now and then aborts a rank at
    # exit ("terminate called without an active exception"). Imported first, they hold none.
    importlib.import_module("torch._dynamo")

    dist.init_process_group(backend=backend, rank=rank, world_size=world_size)
    try:
        yield DistContext(rank, world_size, local_rank, backend)
    finally:
        dist.destroy_process_group()
