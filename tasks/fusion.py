"""Stage ``fusion`` (TYP §4.2–4.5, Tables 1–3; V2VSSC §IV): the collaborative detection benchmark.

The experiments, as training runs and the table cells they fill:

- **Table 1** (TYP Tables 1–2): every method trained on real_cav/train with the true cooperating
  clouds (``oracle``) or with TYP's generated ones (``generated``: same frames, same poses, the
  ego's true cloud, labels cut to the generated extent), all scored on real_cav/test with true
  clouds. No fusion has one row (``ego``): it runs the single-agent detector late fusion trains.
- **Table 3**: pre-train on each of ``pretrain_sources``: the generated target split (``colwaymo``,
  the ColWaymo analogue), simulated source data (``source``, the OPV2V analogue), the two in one
  set (``both``), or not at all (``scratch``), then
  fine-tune on 0, each of ``finetune_scenes`` and all real_cav/train scenarios. One pre-training
  per (source, method) serves every fine-tuning size; scratch on all scenarios is Table 1's
  oracle run; a scratch network fine-tuned on 0 scenes does not exist. The arms differ only in
  where the single-agent detector starts: on n of the N scenarios, fine-tuning and scratch train
  the same steps (:func:`subset_steps`: n / N of the full budget, the same epochs), and the
  warm-started methods start from that run's detector in both. (A fine-tuning budget of 1/20 of
  scratch's, as this stage had, left every pre-trained detector near AP 0 even on all scenes.)
- **Robustness**: the oracle networks, evaluated only (:func:`tasks.fusion_score.robustness`).

Runs (:class:`Run`) are trained once per training seed; the single-agent detector of a data set
(run ``<prefix>-late``) is what early / intermediate fusion of that data start from
(``warm_start``). Runs are trained in dependency order, each saved under
``<out>/models/<run>/seed<k>/`` (safetensors + JSON) and resumable from
``<out>/checkpoints/``. On the CPU, ``processes`` trainings run at once, each in a spawned process
on one thread and started once the network it starts from is saved, the one with the most steps
left on its chain first (:func:`steps_left`): these small networks
keep one core busy each, where one training on two threads gains about a third (on 2 cores, two
at a time train 1.9x the steps per second of one on both). Every training runs on one thread
even alone, so the bytes do not depend on ``processes``. This stage trains and saves the networks
(and ``training.json``: what it ran, in how long); the evaluate stage scores them
(:func:`tasks.fusion_score.score_trained`) and writes the reports
(:func:`tasks.fusion_report.write_report`).
"""
from __future__ import annotations

import concurrent.futures
import functools
import multiprocessing
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tasks.fusion_batch import Inputs
from tasks.fusion_data import FusionDataset, unavailable
from tasks.fusion_train import Trained, load, save, train
from tasks.scene_stage import StageResult
from tasks.training import Trainings, one_thread
from typ import distributed
from typ.config import FusionConfig
from typ.errors import TypError
from typ.formats.opv2v import list_scenarios
from typ.io import SCENARIO_MANIFEST, read_json_or_none, seed_dir, write_json
from typ.registry import METHODS, SINGLE_AGENT, Plot, declare

#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare(
    "fusion", data=("data/sim/real_cav/train", "data/sim/real_cav/test", "data/sim/source/train",
                    "data/generated/real_cav/train", "data/generated/target/pretrain"),
    outs=("artifacts/fusion",),
    plots=(Plot("fusion_loss", "step", {"artifacts/fusion/loss.csv": ["oracle", "generated"]}, "smooth", "step", "loss",
                "single-agent detector training loss, true vs generated cooperating views"),))

#: what pre-training set ``both`` is made of, in this order
BOTH_PARTS = ("colwaymo", "source")
#: Table 3's paired differences, (row, base): each pre-training against scratch, the generated target
#: against source sim (the paper's realism claim) and both against source sim (what adding the
#: generated data to a simulated set gains); a pair is scored where both rows were trained
TABLE3_PAIRS = (("colwaymo", "scratch"), ("source", "scratch"), ("both", "scratch"), ("colwaymo", "source"),
                ("both", "source"))


@dataclass(frozen=True)
class Roots:
    """The OPV2V-layout split folders the benchmark reads."""

    real_train: Path        # real_cav/train: the collaborative training data (V2V4Real analogue)
    real_test: Path         # real_cav/test: every evaluation, true clouds
    generated_cavs: Path    # the same scenarios with TYP-generated cooperating clouds
    source: Path            # simulated source/train (OPV2V analogue)
    colwaymo: Path          # generated target/train: real ego + generated references (ColWaymo analogue)

    @classmethod
    def from_config(cls, cfg: FusionConfig, root: Path) -> "Roots":
        sim, gen = root / cfg.sim, root / cfg.generated
        return cls(sim / cfg.real_domain / cfg.train_split, sim / cfg.real_domain / cfg.test_split,
                   gen / cfg.real_domain / cfg.train_split, sim / cfg.source_domain / cfg.source_split,
                   gen / cfg.colwaymo_domain / cfg.colwaymo_split)


@dataclass(frozen=True)
class Cell:
    """One number of a table: ``method`` run with the networks of training run ``run`` (one per
    seed) lands at ``table[method][row][column]`` (column None: the row is the cell)."""

    table: str
    method: str
    row: str
    column: str | None
    run: str


@dataclass(frozen=True)
class Run:
    """One training run of a trained method's network on training set ``data`` (``real``,
    ``real-<n>`` (the first n scenarios), ``generated``, ``colwaymo``, ``source``, ``both``), from scratch,
    fine-tuned from run ``init`` or warm-started from the single-agent run ``warm``."""

    name: str
    method: str
    data: str
    steps: int
    init: str | None = None
    warm: str | None = None


@dataclass
class Plan:
    """The runs to train (in dependency order), the cells they fill, what was skipped and why."""

    runs: dict[str, Run]
    cells: list[Cell]
    robustness: dict[str, str]          # method -> run whose networks the robustness curves use
    skipped: dict[str, str]             # "<table>/<row>" -> reason
    finetune_sets: dict[str, int | None]

    def add(self, run: Run) -> str:
        self.runs.setdefault(run.name, run)
        return run.name


def finetune_sets(cfg: FusionConfig, n_all: int) -> dict[str, int | None]:
    """Fine-tuning set name -> number of real_cav/train scenarios (0: none, None: all)."""
    return {"0": 0, **{str(n): n for n in sorted(set(cfg.finetune_scenes)) if n < n_all}, "all": None}


def subset_steps(steps: int, count: int | None, n_all: int) -> int:
    """The steps of a run on ``count`` of the ``n_all`` training scenarios (None: all) when a run on
    all of them takes ``steps``: the same epochs, at least one step."""
    return steps if count is None else max(1, round(steps * count / n_all))


def plan(cfg: FusionConfig, roots: Roots) -> Plan:
    """The benchmark's runs and cells for ``cfg.methods`` on the data under ``roots`` (module doc)."""
    n_all = len(list_scenarios(roots.real_train))
    if n_all == 0:
        raise TypError(roots.real_train, "scenarios", "real_cav training scenarios (run the simulate stage)", 0)
    p = Plan({}, [], {}, {}, finetune_sets(cfg, n_all))
    networks = list(dict.fromkeys(METHODS[m].network for m in cfg.methods))

    def warmed(network: str) -> bool:
        return cfg.warm_start and METHODS[network].warm_start

    def scratch(prefix: str, data: str, steps: int, network: str, warm_steps: int | None = None) -> str:
        """``network`` trained on ``data`` without pre-training: warm-started methods from the
        single-agent run of the same data (module doc)."""
        if warmed(network):
            single = p.add(Run(f"{prefix}-{SINGLE_AGENT}", SINGLE_AGENT, data, steps))
            return p.add(Run(f"{prefix}-{network}", network, data,
                             cfg.warm_start_steps if warm_steps is None else warm_steps, warm=single))
        return p.add(Run(f"{prefix}-{network}", network, data, steps))

    def finetuned(prefix: str, source: str, data: str, steps: int, warm_steps: int, network: str) -> str:
        """``network`` fine-tuned on ``data`` from its pre-training on ``source``, as :func:`scratch`
        trains it there: warm-started methods from the fine-tuned single-agent run (module doc)."""
        if warmed(network):
            single = finetuned(prefix, source, data, steps, warm_steps, SINGLE_AGENT)
            return p.add(Run(f"{prefix}-{network}", network, data, warm_steps, warm=single))
        return p.add(Run(f"{prefix}-{network}", network, data, steps, init=f"pretrain-{source}-{network}"))

    def cells(table: str, row: str, column: str | None, run_of: Callable[[str], str]) -> None:
        for m in cfg.methods:
            p.cells.append(Cell(table, m, row, column, run_of(METHODS[m].network)))

    oracle = {n: scratch("oracle", "real", cfg.steps, n) for n in networks}
    for m in cfg.methods:
        p.cells.append(Cell("table1", m, "ego" if METHODS[m].inputs == "ego" else "oracle", None,
                            oracle[METHODS[m].network]))
    reason = unavailable(roots.generated_cavs)
    if reason:
        p.skipped["table1/generated"] = reason
    else:
        generated = {n: scratch("generated", "generated", cfg.steps, n) for n in networks}
        for m in cfg.methods:
            if METHODS[m].inputs != "ego":     # the ego's cloud is never generated
                p.cells.append(Cell("table1", m, "generated", None, generated[METHODS[m].network]))

    for source in cfg.pretrain_sources:
        reason = pretraining_unavailable(roots, source)
        if reason:
            p.skipped[f"table3/{source}"] = reason
            continue
        pre = {n: scratch(f"pretrain-{source}", source, cfg.pretrain_steps, n) for n in networks}
        cells("table3", source, "0", lambda n: pre[n])
        for name, count in p.finetune_sets.items():
            if count == 0:
                continue
            data = "real" if count is None else f"real-{count}"
            steps, warm_steps = (subset_steps(s, count, n_all) for s in (cfg.steps, cfg.warm_start_steps))
            tuned = {n: finetuned(f"finetune{name}-{source}", source, data, steps, warm_steps, n) for n in networks}
            cells("table3", source, name, lambda n: tuned[n])
    for name, count in p.finetune_sets.items():
        if count == 0:
            continue
        runs = oracle if count is None else {
            n: scratch(f"scratch{name}", f"real-{count}", subset_steps(cfg.steps, count, n_all), n,
                       subset_steps(cfg.warm_start_steps, count, n_all)) for n in networks}
        cells("table3", "scratch", name, lambda n: runs[n])
    p.robustness = {m: oracle[METHODS[m].network] for m in cfg.methods}
    return p


def pretraining_unavailable(roots: Roots, source: str) -> str | None:
    """Why pre-training set ``source`` (:data:`typ.config.PRETRAIN_SOURCES`) cannot be read, or None."""
    parts = BOTH_PARTS if source == "both" else (source,)
    return next((f"{part}: {reason}" if source == "both" else reason
                 for part in parts if (reason := unavailable(getattr(roots, part)))), None)


class Benchmark:
    """The runs of one stage execution: training sets read once, networks trained once per seed."""

    def __init__(self, cfg: FusionConfig, roots: Roots, out: Path, *,
                 log_fn: Callable[[dict, int], None] | None = None):
        self.cfg, self.roots, self.out, self.log_fn = cfg, roots, out, log_fn
        self.plan = plan(cfg, roots)
        self._inputs: dict[str, Inputs] = {}
        self.networks: dict[str, list[Trained]] = {}
        self.seconds: dict[str, float] = {}
        self.test = FusionDataset(roots.real_test, **dataset_options(cfg))

    def inputs(self, data: str) -> Inputs:
        """Training set ``data`` (:class:`Run`), read once."""
        if data not in self._inputs:
            self._inputs[data] = read_inputs(self.cfg, self.roots, data)
        return self._inputs[data]

    def train_all(self, trainings: Trainings = Trainings()) -> dict[str, list[Trained]]:
        """Every run of the plan, every seed, in dependency order, on :func:`training_processes`
        processes (module doc); weights under ``<out>/models/``. Each (run, seed) is reported to
        ``trainings`` as ``train-<run>-seed<k>``."""
        jobs = [Job(run, seed, self.out) for run in self.plan.runs.values() if run.name not in self.networks
                for seed in self.cfg.training_seeds]
        workers = training_processes(self.cfg)
        if workers == 1:
            seconds = [trainings.run(job.name, lambda: train_job(self.cfg, job, self.inputs(job.run.data)))
                       for job in jobs]
        else:
            seconds = _train_in_pool(self.cfg, self.roots, jobs, workers, trainings)
        for job, s in zip(jobs, seconds):
            self.seconds[job.run.name] = round(self.seconds.get(job.run.name, 0.0) + s, 3)
        for run in self.plan.runs.values():
            if run.name not in self.networks:
                self.networks[run.name] = [load(self.model_folder(run.name, seed), self.cfg)
                                           for seed in self.cfg.training_seeds]
                if self.log_fn is not None:
                    for t in self.networks[run.name]:
                        for row in t.curve:
                            self.log_fn({f"{run.name}/seed_{t.seed}.{k}": v for k, v in row.items() if k != "step"},
                                        row["step"])
        return self.networks

    def model_folder(self, run: str, seed: int) -> Path:
        return model_folder(self.out, run, seed)

    def curves(self) -> dict[str, dict[str, list[dict]]]:
        """Training curves: run -> seed -> rows of (step, losses, learning rate)."""
        return {name: {str(t.seed): t.curve for t in nets} for name, nets in self.networks.items()}

    def test_inputs(self) -> Inputs:
        """The clean test split as network inputs."""
        return Inputs(list(self.test), self.cfg)


def generated_compose(folder: Path) -> list[str]:
    """What the generated scenarios under ``folder`` are made of (``generate.compose`` as each
    scenario's manifest records it; ``generated`` where it records none)."""
    found = set()
    for scenario in list_scenarios(folder) if folder.is_dir() else []:
        manifest = read_json_or_none(scenario / SCENARIO_MANIFEST) or {}
        found.add(manifest.get("compose", "generated"))
    return sorted(found)


def dataset_options(cfg: FusionConfig) -> dict:
    """How every split is read: the detector's range, communication range, agents, gt rule."""
    return dict(lidar_range=cfg.detector.lidar_range, comm_range=cfg.comm_range, seed=cfg.seed,
                max_agents=cfg.max_agents, min_points=cfg.min_gt_points)


def read_inputs(cfg: FusionConfig, roots: Roots, data: str) -> Inputs:
    """Training set ``data`` of :class:`Run` as network inputs."""
    kw = dataset_options(cfg)
    if data == "real":
        ds = FusionDataset(roots.real_train, **kw)
    elif data.startswith("real-"):
        ds = FusionDataset(roots.real_train, max_scenarios=int(data[len("real-"):]), **kw)
    elif data == "generated":
        ds = FusionDataset(roots.real_train, cav_root=roots.generated_cavs, cav_extent=cfg.generated_extent, **kw)
    elif data == "colwaymo":
        ds = FusionDataset(roots.colwaymo, cav_extent=cfg.generated_extent, **kw)
    elif data == "source":
        ds = FusionDataset(roots.source, **kw)
    elif data == "both":                 # the generated target's frames, then the source's
        return Inputs([s for part in BOTH_PARTS for s in read_inputs(cfg, roots, part).samples], cfg)
    else:
        raise TypError("fusion", "data", "real, real-<n>, generated, colwaymo, source or both", data)
    return Inputs(list(ds), cfg)


# -------------------------------------------------------------- training on processes


@dataclass(frozen=True)
class Job:
    """One training of one run with one seed, saved under ``out/models/<run>/seed<k>``
    (checkpoints under ``out/checkpoints/``); :attr:`init` / :attr:`warm`: the folders of the
    networks it starts from (saved before it is started)."""

    run: Run
    seed: int
    out: Path

    @property
    def folder(self) -> Path:
        return model_folder(self.out, self.run.name, self.seed)

    @property
    def name(self) -> str:
        """What the job is called where it is reported (:class:`tasks.training.Trainings`)."""
        return f"train-{self.run.name}-seed{self.seed}"

    @property
    def init(self) -> Path | None:
        return None if self.run.init is None else model_folder(self.out, self.run.init, self.seed)

    @property
    def warm(self) -> Path | None:
        return None if self.run.warm is None else model_folder(self.out, self.run.warm, self.seed)


def training_processes(cfg: FusionConfig) -> int:
    """How many trainings run at once: ``cfg.processes``, or (0) torch's thread count on the CPU and
    1 on an accelerator or under ``torchrun``."""
    if cfg.processes:
        return cfg.processes
    if distributed.world_size() > 1 or distributed.device().type != "cpu":
        return 1
    return max(1, torch.get_num_threads())


def train_job(cfg: FusionConfig, job: Job, inputs: Inputs) -> float:
    """Train and save ``job``'s network (resumable, as :func:`tasks.fusion_train.train`); its seconds."""
    t0 = time.perf_counter()
    init = None if job.init is None else load(job.init, cfg)
    warm = None if job.warm is None else load(job.warm, cfg)
    with one_thread():
        trained = train(job.run.method, cfg, inputs, steps=job.run.steps, out=job.out,
                        name=f"{job.run.name}/seed_{job.seed}", seed=job.seed, init=init, warm=warm)
    save(trained, job.folder, cfg)
    return time.perf_counter() - t0


def model_folder(out: Path, run: str, seed: int) -> Path:
    """Where run ``run``'s network of seed ``seed`` is saved."""
    return seed_dir(out / "models" / run, seed)


_WORKER_INPUTS: dict[str, Inputs] = {}


def _worker_init() -> None:
    torch.set_num_threads(1)


def _worker_job(cfg: FusionConfig, roots: Roots, job: Job) -> float:
    if job.run.data not in _WORKER_INPUTS:          # each worker reads a training set once
        _WORKER_INPUTS[job.run.data] = read_inputs(cfg, roots, job.run.data)
    return train_job(cfg, job, _WORKER_INPUTS[job.run.data])


def steps_left(jobs: list[Job]) -> list[int]:
    """Per job, its steps plus those of the longest chain of jobs that start from its network: the
    work left on the longest path through it. A step of any detector costs about the same (tiny:
    0.09-0.10 s on one thread), so the pool starts the job with the most left first, as a
    critical-path list scheduler does; started in the plan's order, the pre-training -> fine-tuning
    chains of Table 3 ran last and kept one worker idle (tiny, 2 workers: 758 s against 693 s,
    simulated with the measured run times)."""
    children = {job.folder: [k for k, other in enumerate(jobs) if job.folder in (other.init, other.warm)]
                for job in jobs}

    @functools.cache
    def left(i: int) -> int:
        return jobs[i].run.steps + max((left(k) for k in children[jobs[i].folder]), default=0)

    return [left(i) for i in range(len(jobs))]


def _train_in_pool(cfg: FusionConfig, roots: Roots, jobs: list[Job], workers: int,
                   trainings: Trainings = Trainings()) -> list[float]:
    """``jobs`` on ``workers`` spawned processes, each started when the networks it starts from
    are saved and a worker is free, most steps left first (:func:`steps_left`), and reported to
    ``trainings``; their seconds, in the order of ``jobs``."""
    waiting = list(range(len(jobs)))
    folders = {job.folder for job in jobs}
    done: set[Path] = set()
    seconds = [0.0] * len(jobs)
    running: dict[concurrent.futures.Future, int] = {}
    left = steps_left(jobs)
    ctx = multiprocessing.get_context("spawn")   # no fork of a process whose OpenMP pool runs
    with concurrent.futures.ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init) as pool:
        while waiting or running:
            ready = [i for i in waiting
                     if all(d is None or d not in folders or d in done for d in (jobs[i].init, jobs[i].warm))]
            for i in sorted(ready, key=lambda i: (-left[i], i))[:workers - len(running)]:
                waiting.remove(i)
                future = pool.submit(_worker_job, cfg, roots, jobs[i])
                trainings.started(jobs[i].name, future)
                running[future] = i
            if not running:
                raise TypError("fusion", "plan", "runs whose starting networks are trained first",
                               [jobs[i].run.name for i in waiting])
            finished, _ = concurrent.futures.wait(running, return_when=concurrent.futures.FIRST_COMPLETED)
            for future in finished:
                i = running.pop(future)
                seconds[i] = future.result()        # a worker's error is raised here
                done.add(jobs[i].folder)
    return seconds


TRAINING_JSON = "training.json"


def write_loss_curve(bench: Benchmark, path: Path) -> Path:
    """The single-agent detector's training loss against step on the true and on the generated
    cooperating views (Table 1's runs, first seed) as a ``dvc plots`` table (:func:`typ.plots.loss_curve`):
    columns ``step``, ``oracle``, ``generated`` (empty where a run was not trained)."""
    from typ import plots

    curves = {data: {row["step"]: row["loss"] for row in bench.networks[f"{data}-{SINGLE_AGENT}"][0].curve}
              if f"{data}-{SINGLE_AGENT}" in bench.networks else {} for data in ("oracle", "generated")}
    steps = sorted(set().union(*curves.values()))
    return plots.loss_curve(path, steps, {d: [c.get(k) for k in steps] for d, c in curves.items()})


def training_summary(bench: Benchmark, seconds_total: float) -> dict:
    """What the training stage ran (``<out>/training.json``): runs, trainings, seconds per run, and
    each run's last logged losses (mean over seeds)."""
    last = {}
    for name, nets in bench.networks.items():
        rows = [t.curve[-1] for t in nets if t.curve]
        if rows:
            last[name] = {k: round(float(np.mean([r[k] for r in rows])), 6) for k in ("loss", "cls_loss", "reg_loss")}
    return {"runs": len(bench.plan.runs), "trainings": len(bench.plan.runs) * bench.cfg.seeds,
            "seeds": bench.cfg.seeds, "processes": training_processes(bench.cfg), "seconds_total": round(seconds_total, 3),
            "seconds_training": round(sum(bench.seconds.values()), 3), "seconds_per_run": dict(bench.seconds),
            "final_losses": last}


def load_networks(cfg: FusionConfig, roots: Roots, out: Path) -> dict[str, list[Trained]]:
    """The networks a stage run saved (every run of the plan, every seed); a missing or damaged
    file raises naming it and the stage (what an evaluating stage reads)."""
    p = plan(cfg, roots)
    return {run: [load(model_folder(out, run, seed), cfg) for seed in cfg.training_seeds] for run in p.runs}


def run(cfg, root: Path, *, run, trainings: Trainings = Trainings()) -> StageResult:
    """The stage (:mod:`flows.generic`): every network of the benchmark trained (each a task of
    ``trainings``), ``training.json``, the curves and the loss CSV kept with the MLflow ``run``,
    and Table 1's oracle detectors logged as servable MLflow models; the evaluate stage scores them."""
    from tasks.fusion_serve import ServedDetector

    block = cfg.fusion
    out = Path(root) / block.out
    t0 = time.perf_counter()
    bench = Benchmark(block, Roots.from_config(block, Path(root)), out, log_fn=run.metrics)
    bench.train_all(trainings)
    metrics = training_summary(bench, time.perf_counter() - t0)
    write_json(out / TRAINING_JSON, metrics)
    write_json(out / "curves.json", bench.curves())
    loss = write_loss_curve(bench, out / "loss.csv")
    test = bench.test_inputs()
    for method, oracle in bench.plan.robustness.items():   # Table 1's oracle detectors, servable from MLflow
        served = ServedDetector(bench.networks[oracle][0].as_method(method)).eval()
        run.log_model(f"fusion-{method}", served, ServedDetector.example(method, test))
    return StageResult(metrics, artifacts=[out / TRAINING_JSON, out / "curves.json", loss])
