"""Device, precision and data-parallel training for typ's training stages.

``torchrun --nproc_per_node N -m cli run <stage>`` starts N copies of a training stage. Each
joins the process group from torchrun's environment (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``,
``MASTER_ADDR``/``MASTER_PORT``): gloo on the CPU, nccl on CUDA. Every rank builds the same
model from the same seed and draws the same global batch from ``batch_rng(seed, step)``;
each computes its loss on its shard of that batch (:func:`shard`), and gradients are averaged
across ranks, weighted by shard size, just before every optimizer step. So N ranks take the
step one process takes on the whole global batch, up to float rounding.

Why on the optimizer step and not by wrapping modules in ``DistributedDataParallel``: DDP
syncs gradients only through ``forward``, and typ's stages train through other methods
(``model.loss``, ``encode_pre_quant``, two optimizers in adapt). A step pre-hook on every
optimizer covers them all without changing the stages.

Only rank 0 writes checkpoints, outputs and MLflow runs (:func:`is_main`). Outside torchrun
(``WORLD_SIZE`` unset or 1) everything here is a no-op apart from device and autocast.

On CUDA, :func:`setup` asks for reproducible arithmetic (:func:`reproducible_cuda`): fp32 is
IEEE fp32 (no TF32 rounding of matmul and convolution inputs), cuDNN picks deterministic
algorithms and torch its deterministic kernels where it has them (it warns, once per op, where it
has none: the backward of nearest upsampling in diffusers' UNets, for one).

Devices: a stage's data stays on the CPU (it is small next to the models and drawn with numpy
generators, so batches do not depend on the device). A training step takes its rows with
:func:`local_batch`, which moves them to the runtime device; the modules a loop or a sampler
uses are there while it runs (:func:`on_device`) and go back where they were afterwards, so
evaluation code around the loops works on whatever it is handed.
"""
from __future__ import annotations

import contextlib
import itertools
import os
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np
import torch
import torch.distributed as dist
from torch.optim.optimizer import register_optimizer_step_pre_hook

from typ.errors import TypError

PRECISIONS = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}


@dataclass(frozen=True)
class Runtime:
    """Where this process trains: device, autocast precision, and its place in the group."""

    device: torch.device
    precision: str
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0


_runtime = Runtime(torch.device("cpu"), "fp32")
# this rank's share of the current global batch times world_size (1.0 for equal shards)
_shard_weight = 1.0


def resolve_device(name: str, *, local_rank: int = 0, where: str = "params.yaml") -> torch.device:
    """``auto`` | ``cpu`` | ``cuda`` | ``mps`` -> a device this machine has (``cuda:<local rank>``)."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "mps" if _mps() else "cpu"
    if name == "cuda":
        if not torch.cuda.is_available():
            raise TypError(where, "runtime.device", "a device this machine has (no CUDA here: cpu or auto)", name)
        return torch.device("cuda", local_rank % torch.cuda.device_count())
    if name == "mps" and not _mps():
        raise TypError(where, "runtime.device", "a device this machine has (no MPS here: cpu or auto)", name)
    if name not in ("cpu", "mps"):
        raise TypError(where, "runtime.device", "one of auto, cpu, cuda, mps", name)
    return torch.device(name)


def _mps() -> bool:
    return getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available()


def setup(device: str = "cpu", precision: str = "fp32", *, where: str = "params.yaml") -> Runtime:
    """Pick the device and precision and, under torchrun, join the process group (once)."""
    global _runtime
    if precision not in PRECISIONS:
        raise TypError(where, "runtime.precision", f"one of {list(PRECISIONS)}", precision)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    dev = resolve_device(device, local_rank=local_rank, where=where)
    if dev.type == "cuda":
        reproducible_cuda()
    if world > 1 and not dist.is_initialized():
        if dev.type == "cuda":
            torch.cuda.set_device(dev)
        # on CUDA: nccl for CUDA tensors, gloo for any that stayed on the CPU
        dist.init_process_group("cpu:gloo,cuda:nccl" if dev.type == "cuda" else "gloo", rank=rank, world_size=world)
    _runtime = Runtime(dev, precision, rank, world, local_rank)
    return _runtime


def reproducible_cuda(enabled: bool = True) -> None:
    """CUDA arithmetic that a rerun repeats and a CPU run can be compared with: no TF32, cuDNN's
    deterministic algorithms without autotuning, torch's deterministic kernels where they exist
    (a warning where they do not). ``enabled=False``: the fastest kernels (TF32, cuDNN autotuning)."""
    if enabled:
        # cuBLAS is deterministic only with a fixed workspace, read when its first handle is made
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = not enabled
    torch.backends.cudnn.deterministic = enabled
    torch.backends.cudnn.benchmark = not enabled
    torch.use_deterministic_algorithms(enabled, warn_only=True)


def teardown() -> None:
    """Leave the process group (end of a torchrun process)."""
    global _runtime
    if dist.is_initialized():
        dist.destroy_process_group()
    _runtime = replace(_runtime, rank=0, world_size=1, local_rank=0)


def current() -> Runtime:
    return _runtime


def device() -> torch.device:
    return _runtime.device


def rank() -> int:
    return _runtime.rank


def world_size() -> int:
    return _runtime.world_size


def is_main() -> bool:
    """True on the one process that writes files and MLflow runs (rank 0, or no torchrun)."""
    return _runtime.rank == 0


def autocast() -> contextlib.AbstractContextManager:
    """Autocast to the params' precision on the runtime device; a no-op for fp32."""
    dtype = PRECISIONS[_runtime.precision]
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=_runtime.device.type, dtype=dtype)


def shard(index: Sequence[int] | np.ndarray | torch.Tensor):
    """This rank's part of a global batch ``index`` (every world_size-th item from its rank).

    Batches whose size is not a multiple of the world size give uneven shards; gradients and
    logged values are then weighted by shard size, so the step still equals one process's.
    """
    global _shard_weight
    n, world = len(index), _runtime.world_size
    if world == 1:
        return index
    if n < world:
        raise TypError("params.yaml", "batch_size", f"at least the number of processes ({world})", n)
    local = index[_runtime.rank::world]
    _shard_weight = len(local) * world / n
    return local


def local_batch(*rows):
    """This rank's rows of one global batch: every item (same length) cut at the same positions
    (:func:`shard`); tensors are moved to the runtime device, numpy arrays stay numpy."""
    n = len(rows[0])
    if any(len(r) != n for r in rows):
        raise ValueError(f"local_batch: items of one batch need one length, got {[len(r) for r in rows]}")
    sel = shard(np.arange(n)) if _runtime.world_size > 1 else None
    out = []
    for r in rows:
        if isinstance(r, torch.Tensor):
            out.append((r if sel is None else r[torch.from_numpy(sel).to(r.device)]).to(_runtime.device))
        else:
            out.append(r if sel is None else np.asarray(r)[sel])
    return tuple(out)


def module_device(module: torch.nn.Module) -> torch.device:
    """Where ``module``'s parameters (else buffers) are; the CPU for a module with neither."""
    for t in itertools.chain(module.parameters(), module.buffers()):
        return t.device
    return torch.device("cpu")


@contextlib.contextmanager
def on_device(*modules: torch.nn.Module | None) -> Iterator[torch.device]:
    """While open, ``modules`` (None skipped) are on the runtime device; then each goes back to
    the device it was on. Yields the runtime device."""
    present = [m for m in modules if m is not None]
    before = [module_device(m) for m in present]
    for m in present:
        m.to(_runtime.device)
    try:
        yield _runtime.device
    finally:
        for m, dev in zip(present, before):
            m.to(dev)


def average_gradients(parameters) -> None:
    """Replace each gradient by the shard-weighted mean over ranks, in one all-reduce.

    A parameter without a gradient on some rank counts as zero there; one without a gradient
    on every rank keeps ``grad = None`` (so Adam leaves it alone, as in one process).
    """
    params = [p for p in parameters if p.requires_grad]
    if _runtime.world_size == 1 or not params:
        return
    dev = params[0].device
    flat = torch.cat([(p.grad.detach().reshape(-1).float() * _shard_weight if p.grad is not None
                       else torch.zeros(p.numel(), device=dev)) for p in params]
                     + [torch.tensor([float(p.grad is not None) for p in params], device=dev)])
    dist.all_reduce(flat)
    flat /= _runtime.world_size
    had_grad = flat[-len(params):] > 0
    offset = 0
    for p, keep in zip(params, had_grad.tolist()):
        n = p.numel()
        if keep:
            mean = flat[offset:offset + n].view_as(p).to(p.dtype)
            if p.grad is None:
                p.grad = mean.clone()
            else:
                p.grad.copy_(mean)
        offset += n


def all_reduce_mean(values: dict[str, float]) -> dict[str, float]:
    """Shard-weighted mean over ranks of one step's logged scalars (same keys on every rank)."""
    if _runtime.world_size == 1 or not values:
        return values
    keys = sorted(values)
    t = torch.tensor([float(values[k]) * _shard_weight for k in keys], dtype=torch.float64,
                     device=_collective_device())
    dist.all_reduce(t)
    t /= _runtime.world_size
    return dict(zip(keys, t.tolist()))


def broadcast_object(obj):
    """Rank 0's ``obj`` on every rank (pickled): one starting state for all."""
    if _runtime.world_size == 1:
        return obj
    box = [obj if is_main() else None]
    dist.broadcast_object_list(box, src=0, device=_collective_device())
    return box[0]


def barrier() -> None:
    if _runtime.world_size > 1:
        dist.barrier()


def _collective_device() -> torch.device:
    return _runtime.device if _runtime.device.type == "cuda" else torch.device("cpu")


@contextlib.contextmanager
def synchronized_optimizers() -> Iterator[None]:
    """While open, every optimizer's ``step()`` first averages its parameters' gradients over ranks."""
    if _runtime.world_size == 1:
        yield
        return

    def hook(optimizer, args, kwargs):
        average_gradients(p for group in optimizer.param_groups for p in group["params"])

    handle = register_optimizer_step_pre_hook(hook)
    try:
        yield
    finally:
        handle.remove()


def threaded_map(fn: Callable, items: Iterable, *, workers: int | None = None) -> Iterator:
    """``fn(item)`` of each item, in order, ``workers`` at a time (default: torch's thread count,
    the process's CPU budget), with no more than ``2 * workers`` items in flight. For work that
    releases the GIL (the surfel fit and the ray cast of re-simulation: two threads do 16 views
    in 0.6x the time of one, measured on source pairs, 2 cores); each call is computed alone,
    so the results do not depend on ``workers``."""
    workers = workers or max(1, torch.get_num_threads())
    items = iter(items)
    if workers == 1:
        yield from (fn(item) for item in items)
        return
    with ThreadPoolExecutor(workers) as pool:
        pending: deque = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > 2 * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
