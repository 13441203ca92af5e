"""What every training stage shares: seeded batches, checkpoints, resume, divergence checks.

- Batches are a pure function of ``(seed, step)`` (:func:`batch_rng`), so a run resumed from
  a checkpoint draws exactly the batches an uninterrupted run would have drawn.
- Checkpoints are ``<dir>/step_<NNNNNNNN>.pt``, written to a temporary name and renamed into
  place; the newest complete one is where a crashed run resumes. The last ``keep`` are kept.
- A non-finite loss or gradient norm stops training with :class:`TrainingDiverged`; the last
  good checkpoint stays on disk and no broken model is written.
- Every step's logged scalars are kept in order (:attr:`LoopResult.history`) and saved in each
  checkpoint, so a resumed run ends with the same history as an uninterrupted one; with
  ``curve=`` the loop writes it as the stage's loss curve (:func:`typ.plots.loss_curve`'s
  layout: ``step`` and one column per scalar), the file ``dvc.yaml``'s ``plots:`` draws.
- Under torchrun (:mod:`typ.distributed`) every rank starts from rank 0's state, gradients are
  averaged over ranks at each optimizer step, the logged scalars are the mean over ranks, and
  only rank 0 logs and writes checkpoints. Each step runs under the params' autocast precision.
"""
from __future__ import annotations

import contextlib
import copy
import io
import math
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import torch
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from typ import distributed
from typ.errors import TypError
from typ.io import is_temporary, remove_written, write_bytes

CKPT = re.compile(r"^step_(\d{8})\.pt$")
#: what typ's records name as the writer of a checkpoint (:func:`typ.io.written_by`)
CHECKPOINT = "checkpoint"


class TrainingDiverged(RuntimeError):
    """Loss or gradients became NaN/Inf (or exploded); the last good checkpoint is kept."""


def batch_rng(seed: int, step: int, stream: int = 0) -> np.random.Generator:
    """The generator for one step's batch: independent of how many steps ran before."""
    return np.random.default_rng([seed, stream, step])


def seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)


def checkpoints(directory: Path) -> list[tuple[int, Path]]:
    found = []
    if directory.is_dir():
        for p in directory.iterdir():
            m = CKPT.match(p.name)
            if m:
                found.append((int(m.group(1)), p))
    return sorted(found)


def save_checkpoint(directory: Path, step: int, state: dict, *, keep: int = 2) -> Path:
    path = directory / f"step_{step:08d}.pt"
    save_torch(path, {"step": step, **state}, stage=CHECKPOINT)
    for _, old in checkpoints(directory)[:-keep]:
        remove_written(old, CHECKPOINT)
    return path


def run_checkpoint_dir(root: Path, key: str) -> Path:
    """``root/key``: where this run's checkpoints go. Checkpoints of other keys (another config or
    other data) are removed, so a resume only ever continues the same run: the checkpoints typ
    wrote in the folders beside it and its temporaries there, then each folder that leaves empty;
    anything else is kept."""
    for old in root.glob("*"):
        if old.name != key and not old.name.startswith("."):   # .typ/: typ's records of the checkpoints
            _remove_checkpoints(old)
    return root / key


def drop_checkpoints(folder: Path, *, up_to: Path) -> None:
    """Remove a finished run's checkpoints in ``folder`` (:func:`run_checkpoint_dir`) once its model is
    saved, then the folders up to ``up_to`` that it leaves empty; anything else is kept."""
    _remove_checkpoints(folder)
    parent = folder.parent
    while parent != up_to and up_to in parent.parents and parent.is_dir() and not any(parent.iterdir()):
        parent.rmdir()
        parent = parent.parent


def _remove_checkpoints(folder: Path) -> None:
    """Delete the checkpoints typ wrote in ``folder`` (a folder, not a link; their records match them,
    :func:`typ.io.remove_written`) and typ's temporaries there, then ``folder`` if that empties it."""
    if folder.is_symlink() or not folder.is_dir():
        return
    for p in folder.iterdir():
        if CKPT.match(p.name):
            remove_written(p, CHECKPOINT)
        elif is_temporary(p):
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
    with contextlib.suppress(OSError):  # not empty: it holds what typ did not write
        folder.rmdir()


def save_torch(path: Path, obj: dict, *, stage: str | None = None) -> None:
    """torch.save ``obj`` to ``path`` atomically (temporary name, then rename); with ``stage``,
    recorded as that stage's (:func:`typ.io.atomic_path`)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    write_bytes(path, buf.getvalue(), stage=stage)


def load_latest(directory: Path) -> dict | None:
    """The newest checkpoint of a run (None when there is none), read with ``weights_only``: a
    checkpoint holds tensors, numbers and dicts, never code. A truncated or foreign file raises
    naming it; delete it (or the run's folder) to resume from the one before or start again."""
    found = checkpoints(directory)
    if not found:
        return None
    path = found[-1][1]
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises RuntimeError, EOFError, UnpicklingError, zipfile errors
        raise TypError(path, "file", "a complete training checkpoint (tensors and numbers only; delete it "
                       "to resume from the previous one)", f"{type(exc).__name__}: {str(exc)[:200]}") from None
    if not isinstance(state, dict) or "step" not in state:
        raise TypError(path, "step", "a checkpoint dict with the step it was taken at",
                       type(state).__name__ if not isinstance(state, dict) else sorted(state)[:5])
    return state


@dataclass
class LoopResult:
    steps_run: int
    resumed_from: int
    last: dict[str, float]
    history: list[dict[str, float]]  #: ``{"step": s, **scalars}`` for every step 0..total-1


def write_curve(path: Path, history: list[dict[str, float]]) -> Path:
    """``history`` as a loss-curve table: ``step`` then every scalar, in order of first appearance."""
    from typ.plots import write_records

    return write_records(path, history, columns=["step"])


#: checkpoint key of torch's generators. Code inside a step may draw from them (the EMA
#: quantizer's dead-code restarts and k-means do): a resumed run restores them, or it draws other
#: numbers than the uninterrupted run from the first restart on.
RNG_KEY = "torch_rng"


def rng_state() -> dict[str, torch.Tensor]:
    """torch's CPU generator and, on CUDA, the current device's."""
    state = {"cpu": torch.get_rng_state()}
    if distributed.device().type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state()
    return state


def set_rng_state(state: dict[str, torch.Tensor] | None) -> None:
    """Restore :func:`rng_state`'s generators; ``None`` (a checkpoint from before they were kept): leave them."""
    if state is None:
        return
    torch.set_rng_state(state["cpu"])
    if "cuda" in state and distributed.device().type == "cuda":
        torch.cuda.set_rng_state(state["cuda"])


def state_of(state: Mapping[str, object]) -> dict:
    """``{name: obj.state_dict()}`` of a run's stateful objects (modules, optimizers, EMA shadows)."""
    return {key: obj.state_dict() for key, obj in state.items()}


def load_state(state: Mapping[str, object], saved: dict) -> None:
    """Restore each of ``state``'s objects from ``saved[name]`` (:func:`state_of`'s layout)."""
    for key, obj in state.items():
        obj.load_state_dict(saved[key])


def run_loop(*, name: str, total_steps: int, step_fn: Callable[[int], dict[str, float]],
             state: Mapping[str, object], checkpoint_dir: Path,
             checkpoint_every: int, log_fn: Callable[[dict[str, float], int], None] | None = None,
             grad_norm_limit: float = 1e6, curve: Path | None = None) -> LoopResult:
    """Run ``step_fn(step)`` for steps ``[start, total_steps)``, resuming from the newest checkpoint.

    step_fn returns scalars to log (must include ``loss``; may include ``grad_norm``).
    state: everything a resume needs, by name: objects with ``state_dict`` / ``load_state_dict``
    (models, optimizers, EMA shadows); a checkpoint holds each one's state under its name.
    ``curve``: where to write every step's scalars at the end (:func:`write_curve`), rank 0 only.
    """
    start = 0
    history: list[dict[str, float]] = []
    saved = load_latest(checkpoint_dir)
    if saved is not None:
        history = list(saved.pop("history", []))
        set_rng_state(saved.pop(RNG_KEY, None))
        load_state(state, saved)
        start = int(saved["step"])
    if distributed.world_size() > 1:
        shared = distributed.broadcast_object({"step": start, **state_of(state)})
        load_state(state, shared)
        start = shared["step"]
    main = distributed.is_main()
    last: dict[str, float] = {}
    with distributed.synchronized_optimizers(), \
            Progress(TextColumn(f"[bold]{name}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                     TextColumn("{task.description}"), disable=not main) as bar:
        task = bar.add_task("", total=total_steps, completed=start)
        for step in range(start, total_steps):
            with distributed.autocast():
                values = step_fn(step)
            values = distributed.all_reduce_mean(values)
            bad = [k for k, v in values.items() if not math.isfinite(v)]
            if bad or values.get("grad_norm", 0.0) > grad_norm_limit:
                kept = checkpoints(checkpoint_dir)
                where = f"step_{kept[-1][0]:08d}.pt" if kept else "no checkpoint yet"
                raise TrainingDiverged(f"{name}: step {step}: {', '.join(bad) or 'grad_norm'} = "
                                       f"{[values[k] for k in bad] or values.get('grad_norm')}; "
                                       f"stopped, last good checkpoint: {where}")
            last = values
            history.append({"step": step, **values})
            if log_fn is not None and main:
                log_fn(values, step)
            done = step + 1
            if main and (done % checkpoint_every == 0 or done == total_steps):
                save_checkpoint(checkpoint_dir, done, {**state_of(state), "history": history, RNG_KEY: rng_state()})
            bar.update(task, advance=1, description=f"loss {values['loss']:.4f}")
    if curve is not None and main:
        write_curve(Path(curve), history)
    return LoopResult(total_steps - start, start, last, history)


def learning_rate(peak: float, step: int, total: int, *, warmup: int = 0, schedule: str = "cosine",
                  floor: float = 0.0, end: int | None = None) -> float:
    """The rate of ``step`` (0-based) of a ``total``-step run, every training stage's one schedule:
    a linear warm-up over the first ``warmup`` steps, then ``constant`` at ``peak`` or a ``cosine``
    decay from ``peak`` to ``floor`` × ``peak`` at step ``end`` (default ``total``; ``total - 1``
    reaches the floor on the last step). A function of the step, so a resumed run continues on the
    same curve. Stages 1 and 2 and self-training decay to 10 % at ``total``, the detectors to 1 % on
    their last step, SSC to 0 at ``total`` without warm-up (torch's ``CosineAnnealingLR``)."""
    if step < warmup:
        return peak * (step + 1) / warmup
    end = total if end is None else end
    if schedule == "constant" or end <= warmup:
        return peak
    progress = (step - warmup) / (end - warmup)
    return peak * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0))))


def set_learning_rate(optimizer: torch.optim.Optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr


def noised_batch(rng: np.random.Generator, z0: torch.Tensor, abar: torch.Tensor, batch_size: int):
    """One training batch of the forward process q(z_t | z_0) = N(√ᾱ_t z_0, (1 - ᾱ_t) I).

    Returns (index (B,), t (B,), ε (B, ...), z_t) drawn from ``rng`` alone, so resumed runs
    draw the same batches.
    """
    index = torch.from_numpy(rng.choice(len(z0), size=batch_size, replace=len(z0) < batch_size))
    t = torch.from_numpy(rng.integers(0, len(abar), batch_size))
    eps = torch.from_numpy(rng.standard_normal(z0[index].shape).astype(np.float32))
    return index, t, eps, forward_process(z0[index], t, eps, abar)


def forward_process(z0: torch.Tensor, t: torch.Tensor, eps: torch.Tensor, abar: torch.Tensor) -> torch.Tensor:
    """z_t = √ᾱ_t · z_0 + √(1 - ᾱ_t) · ε (Eq. 4's noised latent), ᾱ indexed by t (B,)."""
    a = abar[t].view(-1, *([1] * (z0.ndim - 1)))
    return a.sqrt() * z0 + (1 - a).sqrt() * eps


def prediction_target(prediction: str, eps: torch.Tensor, z0: torch.Tensor, abar_t: torch.Tensor) -> torch.Tensor:
    """What a network that outputs ``prediction`` (diffusers' names) is trained to return for the
    noised z_t = √ᾱ z_0 + √(1-ᾱ) ε: ``epsilon`` ε, ``sample`` z_0, ``v_prediction`` v = √ᾱ ε -
    √(1-ᾱ) z_0. abar_t: (B,) ᾱ of each sample's t."""
    a = abar_t.view(-1, *([1] * (z0.ndim - 1)))
    return {"epsilon": lambda: eps, "sample": lambda: z0,
            "v_prediction": lambda: a.sqrt() * eps - (1 - a).sqrt() * z0}[prediction]()


def diffusion_loss(output: torch.Tensor, eps: torch.Tensor, z0: torch.Tensor, t: torch.Tensor, abar: torch.Tensor, *,
                   prediction: str, min_snr: float) -> torch.Tensor:
    """Eq. 4 for a network that outputs ``prediction`` (diffusers' names): ``epsilon`` (ε, Eq. 4
    as written), ``sample`` (z_0) or ``v_prediction`` (v = √ᾱ ε - √(1-ᾱ) z_0). The three share
    one minimiser, ε̂ = (z_t - √ᾱ ẑ_0) / √(1-ᾱ); they weigh the timesteps differently. With
    ``min_snr`` > 0 each sample's squared error is weighted by Min-SNR-γ (Hang et al. 2023), in
    ε terms ``min(SNR, γ) / SNR``: ``min(SNR, γ)`` for ``sample``, ``min(SNR, γ) / (SNR + 1)`` for
    ``v_prediction`` (SNR = ᾱ / (1 - ᾱ)); 0 leaves the plain mean squared error."""
    target = prediction_target(prediction, eps, z0, abar[t].to(output.device))
    per_sample = ((output.float() - target) ** 2).flatten(1).mean(1)
    if not min_snr:
        return per_sample.mean()
    snr = (abar[t] / (1 - abar[t])).to(output.device)
    weight = torch.clamp(snr, max=min_snr) / {"epsilon": snr, "sample": torch.ones_like(snr), "v_prediction": snr + 1}[prediction]
    return (per_sample * weight).mean()


class EMA:
    """Exponential moving average of a module's parameters (buffers copied): ``shadow``."""

    def __init__(self, model: torch.nn.Module, decay: float):
        self.decay = decay
        self.shadow = copy.deepcopy(model).eval().requires_grad_(False)

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        for s, p in zip(self.shadow.parameters(), model.parameters()):
            s.lerp_(p.detach(), 1 - self.decay)
        for s, b in zip(self.shadow.buffers(), model.buffers()):
            s.copy_(b)


def grad_norm(parameters) -> float:
    """L2 norm of the gradients. Read after ``optimizer.step()``: under torchrun the step's
    pre-hook has then replaced them by their mean over ranks, the gradient actually applied."""
    norms = [p.grad.detach().norm() for p in parameters if p.grad is not None]
    return float(torch.linalg.vector_norm(torch.stack(norms))) if norms else 0.0


def steps_for(epochs: int, n_items: int, batch_size: int) -> int:
    return max(1, epochs * math.ceil(n_items / batch_size))


class Trainings:
    """Where a stage reports each network it trains, one call per (network, seed).

    :meth:`run` trains one in this process; :meth:`started` is told of one that a process pool
    trains (``future`` resolves to its result, or raises its error). This base class only runs
    them; the flows pass :class:`flows.common.PrefectTrainings`, which makes each one a Prefect
    task run named after it, so the UI shows progress and failures per network."""

    def run(self, name: str, fn: Callable[[], object]) -> object:
        return fn()

    def step(self, name: str, fn: Callable[[], object]) -> object:
        """A stage's other work worth its own line in the UI (encoding, validation, sampling):
        run here; the flows' :class:`flows.common.PrefectTrainings` makes it a Prefect task run."""
        return fn()

    def started(self, name: str, future) -> None:
        """``future``: a :class:`concurrent.futures.Future` of the training called ``name``."""


@contextlib.contextmanager
def one_thread():
    """Every training on the CPU runs on one intra-op thread, so that its bytes do not depend on
    how many run at once; on an accelerator the thread count does not touch the arithmetic."""
    if distributed.device().type != "cpu":
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
