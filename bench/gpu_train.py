"""bench/gpu.py's training phase: the generator at bench/gpu.yaml's size, for as long as the lease allows.

Each network (x VQ-VAE, stage 1, adaptation, stage 2, self-training; the box maps' encoder is
the pooled one of the ``small`` profile and learns nothing) trains through its stage's own
task-level function on the bundle's data (bench/gpu_bundle.py), for its share of the time left:
its steps/s at the training batch is measured first (a few steps), and its epochs are set so
that its steps fill the share. At every checkpoint the newest one is scored on the held-out pairs
(a probe: the x VQ-VAE's reconstruction IoU; stage 1 alone, stage 2 and TYP as the evaluate
stage scores generation, with fewer bootstrap replicates), giving each figure against training
time. The probes' time is not training time. At the end: stage 1 alone, stage 2 (the adapted
source encoder's adapter, no self-training) and TYP scored with the evaluate stage's bootstrap.

A network whose training would pass the deadline is stopped at its next step; the phase then
scores what finished (TYP is then the last complete model) and says what was cut.
"""
from __future__ import annotations

import dataclasses
import math
import multiprocessing
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from pipelines.typ.pipeline_typ import PointStats, TYPPipeline, occupancy_to_points
from tasks import adapt, genscore, selftrain, stage1, stage2, vqvae
from tasks.evaluate import intervals_json
from tasks.training import steps_for
from typ.voxel import Grid

#: each network's share of the training time (the rest of the lease after the final scoring)
SHARES = {"vqvae": 0.22, "stage1": 0.36, "adapt": 0.07, "stage2": 0.15, "selftrain": 0.20}
#: probes (checkpoints scored) per network
PROBES = {"vqvae": 4, "stage1": 2, "adapt": 0, "stage2": 1, "selftrain": 1}
#: bootstrap replicates of a probe's intervals (the final scores take the evaluate block's n_boot)
PROBE_BOOT = 100
#: the figures a probe keeps (the final scores keep every figure)
CURVE_FIGURES = ("iou", "iou_above_ground", "object_hit_rate", "jsd_r2dm")
SEED = 0
#: the methods scored at the end: stage 1 alone, stage 2, TYP
FINAL_METHODS = 3


class DeadlineReached(Exception):
    """The lease's time for training is up."""


# ------------------------------------------------------------------ scoring on worker processes


def _score_one(args) -> genscore.PairScore:
    """One pair's score, as tasks.evaluate_generation.sample_method + score_method compute it."""
    occupancy, truth, seen, boxes, grid, truth_stats, stats, seed = args
    grid = Grid.from_dict(grid)
    points = occupancy_to_points(occupancy, grid, PointStats.from_dict(stats), np.random.default_rng(seed))
    return genscore.score_pair(occupancy, points, truth, seen, boxes, grid, truth_stats)


def scoring_pool(workers: int):
    """Worker processes for the per-pair scores (numpy on the CPU). Forked before any CUDA call:
    call this first."""
    return multiprocessing.get_context("fork").Pool(workers)


@dataclasses.dataclass
class Scorer:
    """Scores generated views of the bundle's held-out pairs, as the evaluate stage does."""

    pairs: object            # tasks.evaluate_generation.EvalSet (no clouds)
    stats: PointStats
    pool: object
    seconds: float = 0.0     #: the last call's wall time, sampling and scoring (what the final scores cost)
    sample_s_per_view: float = 0.0

    def scores(self, occupancy: np.ndarray, seed: int) -> list[genscore.PairScore]:
        p = self.pairs
        jobs = [(occupancy[i], p.x_r[i], p.seen[i], p.boxes[i], p.grid.to_dict(), p.truth_stats[i],
                 self.stats.to_dict(), seed + i) for i in range(len(p))]
        return self.pool.map(_score_one, jobs, chunksize=max(1, len(jobs) // 32))

    def summary(self, rows: list[genscore.PairScore], n_boot: int) -> dict:
        p = self.pairs
        table = genscore.summarize([rows], p.scenes, [s["histogram"] for s in p.truth_stats],
                                   [s["centres"] for s in p.truth_stats], n_boot=n_boot)
        return intervals_json({"m": table})["m"]

    def pipeline(self, pipe: TYPPipeline, *, n_boot: int, seed: int = SEED) -> dict:
        """Sample every pair with ``pipe`` (seed as tasks.evaluate_generation.sample_method) and score."""
        t0 = time.perf_counter()
        occ = pipe.occupancy(self.pairs.x_e, self.pairs.y_r, seed=seed)
        sampled = time.perf_counter() - t0
        out = self.summary(self.scores(occ, seed), n_boot)
        self.seconds, self.sample_s_per_view = time.perf_counter() - t0, sampled / len(self.pairs)
        return {**out, "seconds_sampling_per_view": self.sample_s_per_view, "seconds_scoring": self.seconds - sampled}


# ------------------------------------------------------------------ time


class TrainClock:
    """Training seconds (probes excluded), and the deadline every step is checked against."""

    def __init__(self, deadline: Callable[[], float], reserve: float):
        self.deadline, self.reserve = deadline, reserve
        self.trained = 0.0
        self._since = None

    def start(self) -> None:
        self._since = time.perf_counter()

    def pause(self) -> None:
        if self._since is not None:
            self.trained += time.perf_counter() - self._since
            self._since = None

    def now(self) -> float:
        return self.trained + (time.perf_counter() - self._since if self._since is not None else 0.0)

    def check(self) -> None:
        if self.deadline() < self.reserve:
            raise DeadlineReached


class Probe:
    """A log_fn: keeps the losses, checks the deadline every step, and at every checkpoint scores
    the newest one with ``score(state) -> figures`` (the clock paused meanwhile)."""

    def __init__(self, name: str, clock: TrainClock, every: int, checkpoints: Path, score, curve: list, log):
        self.name, self.clock, self.every, self.root, self.score = name, clock, every, checkpoints, score
        self.curve, self.log = curve, log
        self.losses: list[float] = []

    def __call__(self, values: dict, step: int) -> None:
        self.losses.append(next(v for k, v in values.items() if k.endswith("loss")))
        self.clock.check()
        if self.score is not None and self.every and step and step % self.every == 0:
            self.probe(step)

    def probe(self, step: int, state: dict | None = None) -> None:
        self.clock.pause()
        t0 = time.perf_counter()
        point = {"network": self.name, "step": step, "train_s": round(self.clock.trained, 2)}
        try:
            point |= self.score(newest_checkpoint(self.root) if state is None else state)
            self.log(f"  probe {self.name} step {step}: " + ", ".join(
                f"{k} {v:.3f}" for k, v in point.items() if isinstance(v, float) and k != "train_s"))
        except Exception as exc:   # a probe that cannot score (e.g. nothing generated yet) is a gap, not a stop
            point["error"] = f"{type(exc).__name__}: {exc}"
            self.log(f"  probe {self.name} step {step} failed: {point['error']}")
        finally:
            point["probe_s"] = round(time.perf_counter() - t0, 2)
            self.curve.append(point)
            self.clock.start()


def newest_checkpoint(root: Path) -> dict:
    found = sorted(root.rglob("step_*.pt"), key=lambda p: int(p.stem.split("_")[1]))
    return torch.load(found[-1], map_location="cpu", weights_only=True)


def figures_of(summary: dict) -> dict:
    return {k: summary[k]["value"] for k in CURVE_FIGURES if k in summary}


# ------------------------------------------------------------------ the phase


@dataclasses.dataclass
class Network:
    """What one network's training gave: its result record and its model(s)."""

    record: dict
    model: object = None


class Trainer:
    """The generator's networks one after another (module doc)."""

    def __init__(self, cfg, bundle, scorer: Scorer, *, work: Path, deadline: Callable[[], float], reserve: float,
                 log, record: dict, save):
        self.cfg, self.b, self.scorer, self.work, self.log = cfg, bundle, scorer, work, log
        self.clock = TrainClock(deadline, reserve)
        self.deadline = deadline
        self.record, self.save = record, save
        self.curve = record.setdefault("curve", [])
        self.nets = record.setdefault("networks", {})
        self.pairs_views = _pair_views(bundle.pairs)

    # -- budget

    def steps_for_share(self, name: str, rate: float, overhead: float = 0.0) -> int:
        left = self.deadline() - self.clock.reserve
        remaining = sum(v for k, v in SHARES.items() if k not in self.nets or k == name)
        seconds = max(0.0, left * SHARES[name] / remaining - overhead)
        return max(1, int(seconds * rate))

    def calibrate(self, train: Callable[[int, Callable], object], warmup: int = 2, timed: int = 3) -> float:
        """Steps/s of ``train(steps, log_fn)`` (at least ``warmup + timed`` steps) at the training
        batch, from the steps after the first ``warmup``. Every step checks the deadline, as training
        does: at bench/gpu.yaml's sizes a CPU step can take minutes (a CPU smoke run sat in these five
        steps past its deadline and looked hung)."""
        stamps: list[float] = []

        def log_fn(values: dict, step: int) -> None:
            stamps.append(time.perf_counter())
            self.clock.check()

        self.clock.check()
        train(warmup + timed, log_fn)
        return (len(stamps) - warmup) / max(stamps[-1] - stamps[warmup - 1], 1e-9)

    def run_network(self, name: str, per_epoch: int, rate: float, train: Callable[[int, int, Probe], object],
                    score=None, overhead: float = 0.0, checkpoints: Path | None = None) -> Network:
        """Train ``name`` for its share: ``train(epochs, checkpoint_every, probe)`` -> model."""
        self.clock.check()
        steps = self.steps_for_share(name, rate, overhead)
        epochs = max(1, round(steps / per_epoch))
        total = epochs * per_epoch
        every = max(1, math.ceil(total / (PROBES[name] + 1))) if PROBES[name] else total
        probe = Probe(name, self.clock, every if score is not None else 0, checkpoints or self.work, score,
                      self.curve, self.log)
        rec = self.nets[name] = {"epochs": epochs, "steps_planned": total, "calibrated_steps_per_s": round(rate, 3),
                                 "status": "running"}
        self.log(f"{name}: {epochs} epochs, {total} steps at {rate:.2f} steps/s calibrated "
                 f"({self.deadline():.0f} s left)")
        self.save()
        t0, trained_before = time.perf_counter(), self.clock.trained
        self.clock.start()
        try:
            model = train(epochs, every, probe)
        except DeadlineReached:
            rec.update(status="cut at the deadline", steps_run=len(probe.losses))
            raise
        finally:
            self.clock.pause()
            trained = self.clock.trained - trained_before
            rec.update(seconds=round(time.perf_counter() - t0, 2), train_s=round(trained, 2),
                       steps_run=len(probe.losses), last_loss=probe.losses[-1] if probe.losses else None,
                       steps_per_s=round(len(probe.losses) / trained, 3) if trained > 0 else None)
            self.save()
        rec["status"] = "done"
        if score is not None:
            probe.probe(total, state=None if model is None else {"model": model})
        return Network(rec, model)

    # -- the networks

    def vqvae(self):
        cfg, train = self.cfg, self.b.train
        block = cfg.vqvae
        per_epoch = steps_for(1, len(train), block.batch_size)
        out = self.work / "vqvae"

        def run(epochs, every, log_fn, folder=out, views=train):
            c = dataclasses.replace(block, checkpoint_every=every, x=dataclasses.replace(block.x, epochs=epochs))
            return vqvae.train_one("x", c, views, out=folder, log_fn=log_fn)

        # one step an epoch on a batch's worth of views
        rate = self.calibrate(lambda n, log: run(n, n, log, self.work / "calibrate" / "vqvae",
                                                 train.head(block.batch_size)))

        def score(state):
            model = state["model"] if isinstance(state.get("model"), torch.nn.Module) else self._vq_from(state)
            s = vqvae.evaluate(model, "x", self.pairs_views, threshold=block.threshold, batch_size=8)
            return {"recon_iou": s["iou"], "recon_precision": s["precision"], "recon_recall": s["recall"],
                    "codes_used": s["codes_used"]}

        net = self.run_network("vqvae", per_epoch, rate, lambda e, every, probe: run(e, every, probe), score,
                               checkpoints=out / "x" / "checkpoints")
        y = vqvae.train_one("y", block, train, out=out, log_fn=lambda v, s: None)   # pooled: nothing to learn
        return net.model, y

    def _vq_from(self, state: dict):
        model = vqvae.build("x", self.cfg.vqvae.x, self.b.train.grid.shape[2])
        model.load_state_dict(state["model"])
        return model

    def stage1(self, x_vq, y_enc):
        block = self.cfg.stage1
        t0 = time.perf_counter()
        latents, cond = stage1.encode_views(x_vq, y_enc, self.b.train, dihedral=True)
        encode_s = time.perf_counter() - t0
        views = len(self.b.train)
        per_epoch = steps_for(1, views, block.batch_size)
        out = self.work / "stage1"

        def run(epochs, every, log_fn, folder=out):
            c = dataclasses.replace(block, epochs=epochs, checkpoint_every=every)
            return stage1.train(c, latents, cond, seed=SEED, views=views, out=folder, log_fn=log_fn)

        rate = self.calibrate(lambda n, log: run(math.ceil(n / per_epoch), n, log, self.work / "calibrate" / "stage1"),
                              warmup=2, timed=max(3, per_epoch - 2))
        val_true = torch.from_numpy(self.b.val.occupancy(np.arange(len(self.b.val))))
        _, val_cond = stage1.encode_views(x_vq, y_enc, self.b.val)
        point_stats = PointStats.from_dict(self.b.meta["stats"])

        def pipe_of(model, thresholds):
            return TYPPipeline(x_vq, y_enc, model, None, self.b.train.grid, block.schedule, block.train_timesteps,
                               self.cfg.selftrain.sampler, self.cfg.selftrain.sample_steps, thresholds, point_stats,
                               self.cfg.selftrain.adapter_scale)

        def score(state):
            model = state["model"] if isinstance(state.get("model"), torch.nn.Module) else self._ldm_from(state, latents, cond)
            # probes threshold at 0.5 (tuning takes longer than the probe); the final score uses the tuned thresholds
            return figures_of(self.scorer.pipeline(pipe_of(model.eval(), {"low": 0.5, "high": 0.5, "noise_std": 0.0}),
                                                   n_boot=PROBE_BOOT))

        net = self.run_network("stage1", per_epoch, rate, lambda e, every, probe: run(e, every, probe), score,
                               checkpoints=out / "checkpoints")
        t0 = time.perf_counter()
        logits = stage1.sample_logits(net.model, x_vq, val_cond, cfg=block, generator=torch.Generator().manual_seed(SEED + 1))
        thresholds = stage1.tune_thresholds(logits, val_true, block, SEED)
        net.record.update(encode_s=round(encode_s, 2), tune_s=round(time.perf_counter() - t0, 2), postprocess=thresholds)
        self.save()
        return pipe_of(net.model, thresholds), latents, cond

    def _ldm_from(self, state: dict, latents, cond):
        model = stage1.build(self.cfg.stage1, latents.shape[1], cond.shape[1], latents.shape[-1])
        model.load_state_dict(state["ema"])
        return model

    def adapt(self, x_vq):
        block = self.cfg.adapt
        per_epoch = steps_for(1, len(self.b.source), block.batch_size)
        out = self.work / "adapt"

        def run(epochs, every, log_fn, folder=out):
            c = dataclasses.replace(block, epochs=epochs, checkpoint_every=every)
            return adapt.train(c, x_vq, self.b.source, self.b.train, out=folder, log_fn=log_fn)

        rate = self.calibrate(lambda n, log: run(math.ceil(n / per_epoch), n, log, self.work / "calibrate" / "adapt"),
                              timed=max(3, per_epoch - 2))
        net = self.run_network("adapt", per_epoch, rate, lambda e, every, probe: run(e, every, probe))
        return net.model[0]

    def stage2(self, base: TYPPipeline, source_x):
        block = self.cfg.stage2
        t0 = time.perf_counter()
        data = stage2.encode(self.b.tuples, source_x, base.box_encoder, base.unet, augment=block.augment)
        encode_s = time.perf_counter() - t0
        views = len(self.b.tuples)
        per_epoch = steps_for(1, views, block.batch_size)
        out = self.work / "stage2"

        def run(epochs, every, log_fn, folder=out):
            settings = dataclasses.replace(stage2.settings_of(block, SEED, self.cfg.stage1.min_snr), epochs=epochs,
                                           checkpoint_every=every)
            adapter = stage2.build_adapter(base.unet, res_blocks=block.adapter_res_blocks, seed=SEED)
            return stage2.fit_adapter(adapter, base.unet, base.schedule, base.train_timesteps, data, name="adapter",
                                      settings=settings, views=views, key_extra={}, out=folder, log_fn=log_fn)

        rate = self.calibrate(lambda n, log: run(math.ceil(n / per_epoch), n, log, self.work / "calibrate" / "stage2"),
                              timed=max(3, per_epoch - 2))
        score = self._adapter_score(base)
        net = self.run_network("stage2", per_epoch, rate, lambda e, every, probe: run(e, every, probe), score,
                               checkpoints=out / "checkpoints")
        net.record["encode_s"] = round(encode_s, 2)
        self.save()
        return net.model, rate, encode_s

    def _adapter_score(self, base: TYPPipeline):
        def score(state):
            adapter = state["model"] if isinstance(state.get("model"), torch.nn.Module) else self._adapter_from(base, state)
            return figures_of(self.scorer.pipeline(base.with_adapter(adapter.eval()), n_boot=PROBE_BOOT))
        return score

    def _adapter_from(self, base: TYPPipeline, state: dict):
        adapter = stage2.build_adapter(base.unet, res_blocks=self.cfg.stage2.adapter_res_blocks, seed=SEED)
        adapter.load_state_dict(state["ema"])
        return adapter

    def selftrain(self, base: TYPPipeline, adapter, encoders: selftrain.Encoders, rate: float, overhead: float):
        block = self.cfg.selftrain
        data = selftrain.Inputs(self.b.tuples, self.b.references, selftrain.dummy_ego_tuples(self.b.train),
                                base.point_stats)
        variant = selftrain.variant_of(block)
        views = len(data.tuples) + len(data.references.x_e) * variant.self_training + len(data.dummy) * variant.dummy_ego
        per_epoch = steps_for(1, views, block.batch_size)
        out = self.work / "selftrain"

        def run(epochs, every, log_fn):
            c = dataclasses.replace(self.cfg, selftrain=dataclasses.replace(block, epochs=epochs, checkpoint_every=every))
            return selftrain.enhance(variant, c, data, encoders, base, adapter, seed=SEED, out=out, log_fn=log_fn)[0]

        return self.run_network("selftrain", per_epoch, rate, lambda e, every, probe: run(e, every, probe),
                                self._adapter_score(base), overhead=overhead, checkpoints=out / "checkpoints")


def _pair_views(pairs):
    """The pairs' true reference views as a view set (for the x VQ-VAE's reconstruction IoU)."""
    from gpu_bundle import DenseViews

    return DenseViews(pairs.grid, [(s, str(i), "") for i, s in enumerate(pairs.scenes)], [], pairs.x_r, pairs.y_r)


def run_phase(cfg, bundle, scorer: Scorer, *, work: Path, deadline: Callable[[], float], reserve: float, log,
              record: dict, save) -> TYPPipeline | None:
    """Train every network in turn, then score stage 1 alone, stage 2 and TYP (module doc); the
    last complete generator (None before stage 1 finished)."""
    t = Trainer(cfg, bundle, scorer, work=work, deadline=deadline, reserve=reserve, log=log, record=record, save=save)
    pipes: dict[str, TYPPipeline] = {}
    x_vq = None
    try:
        x_vq, y_enc = t.vqvae()
        base, _, _ = t.stage1(x_vq, y_enc)
        pipes["stage1_only"] = base
        t.clock.reserve = max(reserve, FINAL_METHODS * scorer.seconds * 1.5)   # the final scores cost what a probe did
        source_x = t.adapt(x_vq)
        adapter, rate, encode_s = t.stage2(base, source_x)
        pipes["disc"] = base.with_adapter(adapter)
        # self-training encodes about 1.6x stage 2's tuples and samples its pseudo references first
        overhead = 1.6 * encode_s + len(bundle.references.x_e) * scorer.sample_s_per_view
        st = t.selftrain(base, adapter, selftrain.Encoders(x_vq, source_x, y_enc), rate, overhead)
        pipes["typ"] = base.with_adapter(st.model)
    except DeadlineReached:
        cut = [k for k, v in t.nets.items() if v["status"] != "done"]
        record["cut"] = f"the deadline stopped training at {cut[0] if cut else 'the start of the next network'}"
        log(record["cut"])
    final = record.setdefault("final", {})
    scores = {"vqvae_x": lambda: vqvae.evaluate(x_vq, "x", t.pairs_views, threshold=cfg.vqvae.threshold, batch_size=8)}
    scores |= {name: (lambda p=pipe: scorer.pipeline(p, n_boot=cfg.evaluate.n_boot)) for name, pipe in pipes.items()}
    for name, score in scores.items():
        if name == "vqvae_x" and x_vq is None:
            continue
        try:
            final[name] = score()
            log(f"final {name}: " + ", ".join(f"{k} {v['value'] if isinstance(v, dict) else v:.3f}"
                                              for k, v in final[name].items() if k in (*CURVE_FIGURES, "iou")))
        except Exception as exc:
            final[name] = {"error": f"{type(exc).__name__}: {exc}"}
            log(f"final {name} failed: {final[name]['error']}")
        save()
    record["train_s"] = round(t.clock.trained, 2)
    return pipes.get("typ") or pipes.get("disc") or pipes.get("stage1_only")
