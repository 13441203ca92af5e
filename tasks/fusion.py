"""Stage ``fusion`` (TYP §4.2–4.5, Tables 1–3; V2VSSC §IV): the collaborative detection benchmark.

The experiments, as training runs and the table cells they fill:

- **Table 1** (TYP Tables 1–2): every method trained on real_cav/train with the true cooperating
  clouds (``oracle``) or with TYP's generated ones (``generated``: same frames, same poses, the
  ego's true cloud, labels cut to the generated extent), all scored on real_cav/test with true
  clouds. No fusion has one row (``ego``): it runs the single-agent detector late fusion trains.
- **Table 3**: pre-train on the generated target split (``colwaymo``, the ColWaymo analogue) or
  on simulated source data (``source``, the OPV2V analogue) or not at all (``scratch``), then
  fine-tune on 0, each of ``finetune_scenes`` and all real_cav/train scenarios. One pre-training
  per (source, method) serves every fine-tuning size; scratch on all scenarios is Table 1's
  oracle run; a scratch network fine-tuned on 0 scenes does not exist.
- **Robustness**: the oracle networks, evaluated only (:func:`tasks.fusion_score.robustness`).

Runs (:class:`Run`) are trained once per training seed; the single-agent detector of a data set
(run ``<prefix>-late``) is what early / intermediate fusion of that data start from
(``warm_start``). Runs are trained in dependency order, each saved under
``<out>/models/<run>/seed<k>/`` (safetensors + JSON) and resumable from
``<out>/checkpoints/``. Scoring is :func:`tasks.fusion_score.score` on the trained networks;
reports are :func:`tasks.fusion_report.write_report` of its results.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from models.fusion import METHODS, SINGLE_AGENT
from tasks import fusion_score
from tasks.fusion_batch import Inputs
from tasks.fusion_data import FusionDataset
from tasks.fusion_score import Cell
from tasks.fusion_train import Trained, load, save, train
from typ.config import FusionConfig
from typ.errors import TypError
from typ.formats.opv2v import list_scenarios

PRETRAIN_SOURCES = ("colwaymo", "source")


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


def unavailable(folder: Path) -> str | None:
    """Why ``folder`` holds no scenarios to use (None: it does)."""
    if not folder.is_dir():
        return f"{folder} does not exist (the generate stage writes it)"
    if not list_scenarios(folder):
        return f"{folder} holds no scenario"
    return None


@dataclass(frozen=True)
class Run:
    """One training run of a trained method's network on training set ``data`` (``real``,
    ``real-<n>`` (the first n scenarios), ``generated``, ``colwaymo``, ``source``), from scratch,
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


def plan(cfg: FusionConfig, roots: Roots) -> Plan:
    """The benchmark's runs and cells for ``cfg.methods`` on the data under ``roots`` (module doc)."""
    n_all = len(list_scenarios(roots.real_train))
    if n_all == 0:
        raise TypError(roots.real_train, "scenarios", "real_cav training scenarios (run the simulate stage)", 0)
    p = Plan({}, [], {}, {}, finetune_sets(cfg, n_all))
    networks = list(dict.fromkeys(METHODS[m].network for m in cfg.methods))

    def scratch(prefix: str, data: str, steps: int, network: str) -> str:
        """``network`` trained on ``data`` without pre-training: warm-started methods from the
        single-agent run of the same data (module doc)."""
        if cfg.warm_start and METHODS[network].warm_start:
            single = p.add(Run(f"{prefix}-{SINGLE_AGENT}", SINGLE_AGENT, data, steps))
            return p.add(Run(f"{prefix}-{network}", network, data, cfg.warm_start_steps, warm=single))
        return p.add(Run(f"{prefix}-{network}", network, data, steps))

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

    for source in PRETRAIN_SOURCES:
        reason = unavailable(getattr(roots, source))
        if reason:
            p.skipped[f"table3/{source}"] = reason
            continue
        pre = {n: scratch(f"pretrain-{source}", source, cfg.pretrain_steps, n) for n in networks}
        cells("table3", source, "0", lambda n: pre[n])
        for name, count in p.finetune_sets.items():
            if count == 0:
                continue
            data = "real" if count is None else f"real-{count}"
            tuned = {n: p.add(Run(f"finetune{name}-{source}-{n}", n, data, cfg.finetune_steps, init=pre[n]))
                     for n in networks}
            cells("table3", source, name, lambda n: tuned[n])
    for name, count in p.finetune_sets.items():
        if count == 0:
            continue
        runs = oracle if count is None else {n: scratch(f"scratch{name}", f"real-{count}", cfg.steps, n)
                                             for n in networks}
        cells("table3", "scratch", name, lambda n: runs[n])
    p.robustness = {m: oracle[METHODS[m].network] for m in cfg.methods}
    return p


class Benchmark:
    """The runs of one stage execution: training sets read once, networks trained once per seed."""

    def __init__(self, cfg: FusionConfig, roots: Roots, out: Path, *,
                 log_fn: Callable[[dict, int], None] | None = None):
        self.cfg, self.roots, self.out, self.log_fn = cfg, roots, out, log_fn
        self.plan = plan(cfg, roots)
        self._inputs: dict[str, Inputs] = {}
        self.networks: dict[str, list[Trained]] = {}
        self.seconds: dict[str, float] = {}
        self.test = FusionDataset(roots.real_test, **self._dataset_options())

    def _dataset_options(self) -> dict:
        c = self.cfg
        return dict(lidar_range=c.detector.lidar_range, comm_range=c.comm_range, seed=c.seed, max_agents=c.max_agents,
                    min_points=c.min_gt_points)

    def inputs(self, data: str) -> Inputs:
        """Training set ``data`` (:class:`Run`), read once."""
        if data not in self._inputs:
            c, r = self.cfg, self.roots
            kw = self._dataset_options()
            if data == "real":
                ds = FusionDataset(r.real_train, **kw)
            elif data.startswith("real-"):
                ds = FusionDataset(r.real_train, max_scenarios=int(data[len("real-"):]), **kw)
            elif data == "generated":
                ds = FusionDataset(r.real_train, cav_root=r.generated_cavs, cav_extent=c.generated_extent, **kw)
            elif data == "colwaymo":
                ds = FusionDataset(r.colwaymo, cav_extent=c.generated_extent, **kw)
            elif data == "source":
                ds = FusionDataset(r.source, **kw)
            else:
                raise TypError("fusion", "data", "real, real-<n>, generated, colwaymo or source", data)
            self._inputs[data] = Inputs(list(ds), c)
        return self._inputs[data]

    def train_all(self) -> dict[str, list[Trained]]:
        """Every run of the plan, every seed, in dependency order; weights under ``<out>/models/``."""
        for run in self.plan.runs.values():
            if run.name in self.networks:
                continue
            t0 = time.perf_counter()
            nets = []
            for k, seed in enumerate(self.cfg.training_seeds):
                init = None if run.init is None else self.networks[run.init][k]
                warm = None if run.warm is None else self.networks[run.warm][k]
                trained = train(run.method, self.cfg, self.inputs(run.data), steps=run.steps, out=self.out,
                                name=f"{run.name}/seed{seed}", seed=seed, init=init, warm=warm, log_fn=self.log_fn)
                save(trained, self.model_folder(run.name, seed), self.cfg)
                nets.append(trained)
            self.networks[run.name] = nets
            self.seconds[run.name] = round(time.perf_counter() - t0, 3)
        return self.networks

    def model_folder(self, run: str, seed: int) -> Path:
        return self.out / "models" / run / f"seed{seed}"

    def score(self, progress: Callable[[str], None] | None = None) -> dict:
        """:func:`tasks.fusion_score.score` of the trained networks, with what the stage ran."""
        results = fusion_score.score(self.cfg, self.test, self.networks, self.plan.cells, self.plan.robustness,
                                     progress=progress)
        return {**results, "skipped": dict(self.plan.skipped),
                "finetune_sets": {k: ("all" if v is None else v) for k, v in self.plan.finetune_sets.items()},
                "train_frames": len(self.inputs("real")), "train_scenarios": len(set(self.inputs("real").scenarios)),
                "runs": len(self.plan.runs), "trainings": len(self.plan.runs) * self.cfg.seeds,
                "seconds_per_run": dict(self.seconds)}

    def curves(self) -> dict[str, dict[str, list[dict]]]:
        """Training curves: run -> seed -> rows of (step, losses, learning rate)."""
        return {name: {str(t.seed): t.curve for t in nets} for name, nets in self.networks.items()}

    def test_inputs(self) -> Inputs:
        """The clean test split as network inputs."""
        return Inputs(list(self.test), self.cfg)


def load_networks(cfg: FusionConfig, roots: Roots, out: Path) -> dict[str, list[Trained]]:
    """The networks a stage run saved (every run of the plan, every seed); a missing or damaged
    file raises naming it and the stage (what an evaluating stage reads)."""
    p = plan(cfg, roots)
    return {run: [load(out / "models" / run / f"seed{seed}", cfg) for seed in cfg.training_seeds] for run in p.runs}
