"""Stage ``ssc``: collaborative semantic scene completion (V2VSSC §III–IV, Table I, Figs. 4–5).

Data: the fusion samples of :class:`tasks.fusion_data.FusionDataset` (OPV2V layout, 70 m
communication range, delay and pose noise as there) on V2VSSC's grid, each with the semantic
occupancy maps the simulate stage writes beside the clouds (:mod:`typ.ssc`).

Networks (:func:`models.ssc.ssc_detector`, PointPillars with an occupancy head) are reached through
the fusion-method registry of ``models/fusion.py``, as the detectors are:

- ``single``: under :class:`models.fusion.NoFusion`, trained on every agent's own cloud against its
  own map. No fusion runs it on the ego's cloud; late fusion runs it on every agent in range and
  merges the maps in the ego frame, keeping per voxel the most confident agent
  (:func:`models.ssc.merge_max_confidence`), as V2VSSC does.
- ``early``, ``attfuse`` and ``v2xvit``: :class:`~models.fusion.EarlyFusion` (the agents' clouds
  merged in the ego frame), :class:`~models.fusion.AttFuse` (features warped and attended in the
  ego frame) and :class:`~models.fusion.V2XViT` (its transformer, the block ``ssc.v2xvit``, on the
  backbone's features, with an occupancy head on its width), warm-started from the single-agent
  network and trained on the ego's map.

Loss: cross-entropy weighted ``1 / ln(eps + share)`` (:func:`models.ssc.class_weights`, the shares
of the training maps' classes), Adam with cosine decay, one view or sample a step in a seeded order.
Every network is saved (safetensors + JSON) with a key of its training config, seed, init and
data, and a rerun loads instead of training when the key matches: a stage killed mid-way resumes
from the last network it finished. Each (data, seed) pair's networks train on one thread, the
pairs on as many spawned processes as torch has threads (:func:`train_arms`), as the fusion
stage's runs do: on 2 cores two one-thread trainings do 1.9x the steps per second of one on both,
and the bytes do not depend on how many run at once.

Scores: :func:`typ.metrics.ssc_scores` of the ego's maps against the ego's truth, counts pooled
over the test frames (SemanticKITTI), intervals from a bootstrap over test scenarios and seeds.
"""
from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from models.fusion import FusionModule, NoFusion, build, compressed, get_method, merge_agent_points
from models.pointpillars import PointPillars
from models.ssc import SSC_LIDAR_RANGE, class_weights, merge_max_confidence, ssc_detector, warp_to_ego
from tasks.artifacts import load_if_key, save_module
from tasks.fusion_data import FusionDataset, FusionSample, unavailable
from tasks.training import one_thread, seed_everything
from typ import distributed
from typ.config import SSC_METHODS, SscConfig
from typ.errors import TypError
from typ.io import hash_obj
from typ.metrics.intervals import bootstrap
from typ.metrics.ssc import SSC_CLASSES, ssc_confusion, ssc_scores
from typ.ssc import SSC_GRID, occupancy_path, read_occupancy

STAGE = "ssc"
#: the network each method runs (no and late fusion share the single-agent one)
NETWORK = {"none": "single", "early": "early", "late": "single", "attfuse": "attfuse", "v2xvit": "v2xvit"}
#: display names of the methods, V2VSSC Table I's rows
DISPLAY = {"none": "No Fusion", "early": "Early Fusion", "late": "Late Fusion", "attfuse": "Intermediate (AttFuse)",
           "v2xvit": "Intermediate (V2X-ViT)"}
#: the figures scored, each with an interval: geometric, semantic and per class
FIGURES = ("iou", "miou", "ciou", "precision", "recall", *(f"iou_{c}" for c in SSC_CLASSES[1:]))
N_CLASSES = len(SSC_CLASSES)
assert set(NETWORK) == set(SSC_METHODS)


def ssc_dataset(root, **kw) -> FusionDataset:
    """:class:`FusionDataset` of a split folder on V2VSSC's range (other options as there)."""
    return FusionDataset(root, lidar_range=SSC_LIDAR_RANGE, **kw)


def sample_maps(ds: FusionDataset, i: int, sample: FusionSample | None = None) -> list[np.ndarray]:
    """(X, Y, Z) uint8 maps of sample ``i``'s agents, each in its own frame at the frame its cloud
    was sent (the ego's: now); index 0 is the ego's ground truth."""
    sample = ds[i] if sample is None else sample
    s, t = ds.index[i]
    folder, _, stamps = ds.scenarios[s]
    return [read_occupancy(occupancy_path(folder, agent, stamps[t - int(d)]))
            for agent, d in zip(sample.agent_ids, sample.time_delay)]


def ego_map(ds: FusionDataset, i: int, sample: FusionSample) -> np.ndarray:
    """The ego's true (X, Y, Z) map of sample ``i`` (its current frame)."""
    return read_occupancy(occupancy_path(ds.scenarios[ds.index[i][0]][0], sample.agent_ids[0], sample.timestamp))


def model_kwargs(block: SscConfig) -> dict:
    """:func:`models.ssc.ssc_detector` arguments of the config's network."""
    n = block.network
    return dict(layer_nums=tuple(n.layer_nums), num_filters=tuple(n.num_filters),
                num_upsample_filters=tuple(n.num_upsample_filters), pillar_channels=n.pillar_channels,
                head_hidden=n.head_hidden, max_pillars=n.max_pillars)


# ---------------------------------------------------------------- training data


#: the label ignored by the loss (voxels a generated view is not scored on)
IGNORE = 255
#: BEV cells (0.78 m) around a generated view's points that its map is scored on (``footprint``)
FOOTPRINT_CELLS = 2


def footprint(cloud: np.ndarray, cells: int = FOOTPRINT_CELLS) -> np.ndarray:
    """(X, Y) bool: the map columns within ``cells`` columns of one of ``cloud``'s points (own frame)."""
    from scipy import ndimage

    idx = np.floor((np.asarray(cloud[:, :2], dtype=np.float64) - SSC_GRID.lower[:2]) / SSC_GRID.voxel[:2]).astype(int)
    shape = SSC_GRID.shape[:2]
    keep = np.all((idx >= 0) & (idx < np.asarray(shape)), axis=1)
    hit = np.zeros(shape, dtype=bool)
    hit[idx[keep, 0], idx[keep, 1]] = True
    disc = np.hypot(*np.mgrid[-cells:cells + 1, -cells:cells + 1]) <= cells
    return ndimage.binary_dilation(hit, structure=disc)


@dataclass
class TrainingSet:
    """What the networks learn from: every agent's (cloud, own map) and every sample with its ego
    map; ``ego[k]``: view ``k`` is a sample's ego (its cloud is never generated)."""

    views: list[tuple[np.ndarray, np.ndarray]]
    samples: list[FusionSample]
    ego_maps: list[np.ndarray]
    key: str = ""
    ego: list[bool] = field(default_factory=list)

    @classmethod
    def read(cls, ds: FusionDataset) -> "TrainingSet":
        views, samples, maps, ego = [], [], [], []
        ident = []
        for i in range(len(ds)):
            sample = ds[i]
            own = sample_maps(ds, i, sample)
            views += list(zip(sample.clouds, own))
            ego += [j == 0 for j in range(len(own))]
            samples.append(sample)
            maps.append(own[0])
            ident.append((sample.scenario, sample.timestamp, list(sample.agent_ids), [len(c) for c in sample.clouds],
                          round(float(sum(np.sum(c[:, :3], dtype=np.float64) for c in sample.clouds)), 2),
                          [int(np.count_nonzero(m)) for m in own], [int(m.sum(dtype=np.int64)) for m in own]))
        if not views:
            raise TypError(ds.root, "samples", "at least one training sample", "none")
        return cls(views, samples, maps, hash_obj(ident)[:16], ego)

    def class_counts(self) -> np.ndarray:
        """Voxels of each class over every agent's map (ignored voxels left out)."""
        return sum(np.bincount(m.reshape(-1), minlength=IGNORE + 1)[:N_CLASSES] for _, m in self.views)

    def with_generated_views(self, mode: str) -> "TrainingSet":
        """What the single-agent network learns of a set whose cooperating clouds are generated
        (``ssc.generated_views``): ``all`` every view on its whole map; ``footprint`` the generated
        views scored only on the columns near their points (:func:`footprint`; the rest
        :data:`IGNORE`); ``ego`` the ego views only. The samples (the fused networks') are kept."""
        if mode == "all":
            return self
        if mode not in ("ego", "footprint"):
            raise TypError("tasks.ssc.TrainingSet", "generated_views", "all, footprint or ego", mode)
        views, ego = [], []
        for (c, m), e in zip(self.views, self.ego):
            if not e:
                seen = footprint(c) if mode == "footprint" else None
                if seen is None or not seen.any():   # ego mode, or a generated view with no point in the grid
                    continue
                m = np.where(seen[:, :, None], m, np.uint8(IGNORE))
            views.append((c, m))
            ego.append(e)
        extra = {"footprint_cells": FOOTPRINT_CELLS} if mode == "footprint" else {}
        return TrainingSet(views, self.samples, self.ego_maps, hash_obj([self.key, mode, extra])[:16], ego)


def _fit(model: FusionModule, step: Callable[[int, torch.device], tuple[torch.Tensor, np.ndarray]], n_items: int, *,
         steps: int, seed: int, lr: float, weights: np.ndarray, name: str) -> list[float]:
    """``steps`` Adam steps (cosine decay) of class-weighted cross-entropy, item ``k`` of a seeded
    order each (every item once before any twice); ``step(k, device)`` -> (logits (1, K, X, Y, Z),
    labels), the inputs on ``device``. The model trains on the runtime device under its autocast
    precision and ends where it was."""
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps)
    order = np.random.default_rng(seed).permutation(np.resize(np.arange(n_items), steps))
    losses = []
    with distributed.on_device(model) as dev:
        w = torch.tensor(weights, dtype=torch.float32, device=dev)
        model.train()
        for n, k in enumerate(order):
            with distributed.autocast():
                logits, labels = step(int(k), dev)
            labels = torch.as_tensor(labels, dtype=torch.long).to(dev)[None]
            loss = F.cross_entropy(logits.float(), labels, weight=w, ignore_index=IGNORE)
            if not torch.isfinite(loss):
                raise TypError(f"{STAGE}:{name}", "loss", "a finite training loss", f"{loss.item()} at step {n}")
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
    model.eval()
    return losses


def _on(tensors: dict, device: torch.device) -> dict:
    """Every tensor of ``tensors`` on ``device`` (other values as they are)."""
    return {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in tensors.items()}


def train_single(data: TrainingSet, *, steps: int, seed: int, lr: float, model_kw: dict,
                 weights: np.ndarray) -> tuple[NoFusion, list[float]]:
    """The single-agent network, one agent view (its own cloud, its own map) a step."""
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise TypError("tasks.ssc.train_single", "steps", "an integer >= 1", steps)
    seed_everything(seed)
    det = ssc_detector(**model_kw)
    model = NoFusion(detector=det)
    one = torch.ones(1, 1, dtype=torch.bool)

    def step(k: int, dev: torch.device):
        cloud, labels = data.views[k]
        return model(_on(det.pillarize([cloud]), dev), agent_mask=one.to(dev))["occ"], labels

    return model, _fit(model, step, len(data.views), steps=steps, seed=seed, lr=lr, weights=weights, name="single")


def _inputs(det: PointPillars, method: str, sample: FusionSample) -> tuple[dict, dict]:
    """(pillars, forward keywords) of one sample for ``method``'s module (batch of one), pillarized by
    ``det`` (the single-agent network's detector: every network shares its pillar grid)."""
    if method == "early":
        return det.pillarize([merge_agent_points(sample.clouds, sample.transforms)]), \
            {"agent_mask": torch.ones(1, 1, dtype=torch.bool)}
    n = len(sample.clouds)
    return det.pillarize(list(sample.clouds)), {
        "agent_mask": torch.ones(1, n, dtype=torch.bool),
        "transforms": torch.from_numpy(np.asarray(sample.transforms, dtype=np.float64))[None],
        "time_delay": torch.as_tensor(np.asarray(sample.time_delay), dtype=torch.long)[None]}


def train_fused(method: str, data: TrainingSet, single: NoFusion, *, steps: int, seed: int, lr: float,
                weights: np.ndarray, options: dict | None = None) -> tuple[FusionModule, list[float]]:
    """Early fusion, AttFuse or V2X-ViT from the single-agent network, one sample (ego map) a step;
    ``options``: the module's extra arguments (V2X-ViT's transformer)."""
    if NETWORK.get(method, "single") == "single":
        raise TypError("tasks.ssc.train_fused", "method",
                       "early, attfuse or v2xvit (a network trained on the ego's map)", method)
    seed_everything(seed)
    module = build(method, copy.deepcopy(single.detector), options)
    module.warm_start(single.detector)

    def step(k: int, dev: torch.device):
        pillars, kw = _inputs(single.detector, method, data.samples[k])
        return module(_on(pillars, dev), **_on(kw, dev))["occ"], data.ego_maps[k]

    return module, _fit(module, step, len(data.samples), steps=steps, seed=seed, lr=lr, weights=weights, name=method)


@dataclass
class SscNetworks:
    """The trained networks of one seed, by network name (:data:`NETWORK`)."""

    seed: int
    networks: dict[str, FusionModule]
    losses: dict[str, list[float]] = field(default_factory=dict)
    keys: dict[str, str] = field(default_factory=dict)

    def for_method(self, method: str) -> FusionModule:
        return self.networks[NETWORK[method]]


def _lists(d: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


def network_options(block: SscConfig, name: str) -> dict | None:
    """The extra module arguments of network ``name`` (the config block the registry names: V2X-ViT's
    ``v2xvit``), as JSON; None where the module takes none."""
    option_block = None if name == "single" else get_method(name).options
    return None if option_block is None else _lists(asdict(getattr(block, option_block)))


def _network_config(name: str, model_kw: dict, options: dict | None = None) -> dict:
    config = {"network": name, "model": _lists(model_kw)}
    return config if options is None else {**config, "options": options}


def _build(config: dict) -> FusionModule:
    kw = {k: tuple(v) if isinstance(v, list) else v for k, v in config["model"].items()}
    name = config["network"]
    det = ssc_detector(**kw)
    return NoFusion(detector=det) if name == "single" else build(name, det, config.get("options"))


def train_seed(block: SscConfig, data: TrainingSet, weights: np.ndarray, seed: int, out: Path,
               log: Callable[[str], None] = print, *, data_name: str = "oracle") -> SscNetworks:
    """Every network the config's methods need, for ``seed``, trained on ``data`` (``data_name``:
    oracle or generated): loaded from ``out/models/<data_name>`` when a network with the same key
    is there (a finished or earlier run), trained and saved otherwise."""
    model_kw = model_kwargs(block)
    needed = ["single"] + [NETWORK[m] for m in block.methods if NETWORK[m] != "single"]
    options = {name: network_options(block, name) for name in needed}
    result = SscNetworks(seed, {})
    base = {"data": data.key, "model": _network_config("single", model_kw)["model"], "seed": seed,
            "eps": block.class_weight_eps}
    for name in dict.fromkeys(needed):
        if name == "single":
            key = hash_obj({**base, "steps": block.steps, "lr": block.lr})[:16]
        else:   # a module without options keeps the key it had before options were keyed
            extra = {} if options[name] is None else {"options": options[name]}
            key = hash_obj({**base, "network": name, "init": result.keys["single"], "steps": block.warm_start_steps,
                            "lr": block.finetune_lr, "comm_range": block.comm_range, **extra})[:16]
        folder = out / "models" / data_name / f"{name}-seed{seed}"
        loaded = load_if_key(folder, _build, STAGE, key)
        if loaded is not None:
            module, meta = loaded
            result.networks[name], result.losses[name] = module, list(meta.get("losses", []))
            log(f"ssc: {data_name} {name} seed {seed} loaded from {folder} "
                f"(key {key}: trained by a worker or an earlier run)")
        else:
            with one_thread():
                if name == "single":
                    module, losses = train_single(data, steps=block.steps, seed=seed, lr=block.lr, model_kw=model_kw,
                                                  weights=weights)
                else:
                    module, losses = train_fused(name, data, result.networks["single"],
                                                 steps=block.warm_start_steps, seed=seed, lr=block.finetune_lr,
                                                 weights=weights, options=options[name])
            save_module(folder, module, _network_config(name, model_kw, options[name]), key=key, seed=seed,
                        losses=[round(v, 6) for v in losses])
            result.networks[name], result.losses[name] = module, losses
        result.keys[name] = key
    return result


def generated_root(block: SscConfig, root: Path) -> Path:
    """Where the generated arm's cooperating clouds are: the generate stage's training split."""
    return Path(root) / block.generated / block.domain / block.train_split


def training_set(block: SscConfig, root: Path, data_name: str) -> TrainingSet:
    """The training set of arm ``data_name``: ``oracle`` (every agent's true cloud) or
    ``generated`` (the cooperating clouds under :func:`generated_root`, the single-agent
    network's views chosen by ``block.generated_views``)."""
    train = Path(root) / block.sim / block.domain / block.train_split
    if data_name == "oracle":
        return TrainingSet.read(ssc_dataset(train, comm_range=block.comm_range))
    return TrainingSet.read(ssc_dataset(train, comm_range=block.comm_range, cav_root=generated_root(block, root))
                            ).with_generated_views(block.generated_views)


def _train_arm(block: SscConfig, root: Path, data_name: str, seed: int, weights: np.ndarray) -> str:
    torch.set_num_threads(1)
    train_seed(block, training_set(block, root, data_name), weights, seed, Path(root) / block.out,
               log=lambda _: None, data_name=data_name)
    return f"{data_name} seed {seed}"


def train_arms(block: SscConfig, root: Path, arms: Sequence[str], weights: np.ndarray,
               log: Callable[[str], None] = print) -> None:
    """Train (or find by key) every network of each arm in ``arms`` and each seed, the (arm, seed)
    pairs on spawned one-thread processes, as many at once as torch has threads (module doc);
    :func:`train_seed` then loads them. With one thread or one pair nothing is spawned: train_seed
    trains them itself, on one thread as well."""
    import concurrent.futures
    import multiprocessing

    jobs = [(arm, seed) for seed in block.training_seeds for arm in arms]
    workers = min(len(jobs), torch.get_num_threads())
    if workers < 2:
        return
    ctx = multiprocessing.get_context("spawn")    # no fork of a process whose OpenMP pool runs
    with concurrent.futures.ProcessPoolExecutor(workers, mp_context=ctx) as pool:
        futures = [pool.submit(_train_arm, block, Path(root), arm, seed, weights) for arm, seed in jobs]
        for future in futures:                    # a worker's error is raised here
            log(f"ssc: the networks of {future.result()} are trained")


# ---------------------------------------------------------------- prediction and scores


@torch.no_grad()
def _predict_own(model: NoFusion, clouds: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """(L, X, Y, Z) labels and max-softmax confidences of each cloud in its own frame."""
    det = model.detector
    mask = torch.ones(len(clouds), 1, dtype=torch.bool)
    probs = model(det.pillarize(list(clouds)), agent_mask=mask)["occ"].softmax(1)
    conf, labels = probs.max(1)
    return labels, conf


@torch.no_grad()
def predict(nets: SscNetworks, sample: FusionSample, method: str, *, bits: int | None = None) -> np.ndarray:
    """(X, Y, Z) uint8 ego-frame map of ``sample`` by ``method`` (:data:`NETWORK`); ``bits``: AttFuse's
    messages quantised to that many bits."""
    if method not in NETWORK:
        raise TypError("tasks.ssc.predict", "method", f"one of {list(NETWORK)}", method)
    module = nets.for_method(method)
    if method in ("none", "late"):
        clouds = sample.clouds[:1] if method == "none" else sample.clouds
        labels, conf = _predict_own(module, clouds)
        if method == "none":
            return labels[0].numpy().astype(np.uint8)
        kw = dict(lower=SSC_GRID.lower, voxel=SSC_GRID.voxel.tolist())
        warped = [warp_to_ego(labels[j], conf[j], sample.transforms[j], **kw) for j in range(len(clouds))]
        merged, _ = merge_max_confidence(torch.stack([w[0] for w in warped]), torch.stack([w[1] for w in warped]))
        return merged.numpy().astype(np.uint8)
    pillars, kw = _inputs(nets.networks["single"].detector, method, sample)
    with compressed(module, bits):
        logits = module(pillars, **kw)["occ"]
    return logits[0].argmax(0).numpy().astype(np.uint8)


def confusions(nets: SscNetworks, ds: FusionDataset, method: str, *, bits: int | None = None) -> tuple[np.ndarray, dict]:
    """Per-scenario (S, K, K) confusion matrices of ``method``'s ego maps against the ego's truth over
    ``ds`` (rows truth, columns prediction), and what was scored (frames, mean message age)."""
    conf = np.zeros((len(ds.scenarios), N_CLASSES, N_CLASSES), dtype=np.int64)
    ages = []
    for i in range(len(ds)):
        sample = ds[i]
        pred = predict(nets, sample, method, bits=bits)
        conf[ds.index[i][0]] += ssc_confusion(pred, ego_map(ds, i, sample), N_CLASSES)
        ages += [100.0 * float(d) for d in sample.time_delay[1:]]
    return conf, {"frames": len(ds), "applied_delay_ms": float(np.mean(ages)) if ages else 0.0}


def figure_of(scores: dict, name: str) -> float:
    """One of :data:`FIGURES` from :func:`typ.metrics.ssc_scores`' dict."""
    if name.startswith("iou_"):
        return float(scores["iou_per_class"][SSC_CLASSES.index(name[4:]) - 1])
    return float(scores[name])


def intervals(conf: np.ndarray, *, n_boot: int, seed: int = 0,
              figures: Sequence[str] = FIGURES) -> dict[str, dict[str, float]]:
    """Each of ``figures`` (:data:`FIGURES`) with its bootstrap interval, from (seeds, scenarios, K, K)
    confusion matrices: the mean over seeds of the figure pooled over scenarios, scenarios and seeds
    resampled."""
    conf = np.asarray(conf)
    if conf.ndim == 3:
        conf = conf[None]

    def stat_of(name: str):
        def stat(c: np.ndarray, s: np.ndarray) -> float:
            return float(np.mean([figure_of(ssc_scores(conf[k][c].sum(0)), name) for k in s]))
        return stat

    return {name: bootstrap(stat_of(name), conf.shape[1], conf.shape[0], n_boot=n_boot, seed=seed).to_dict()
            for name in figures}


#: the figures given per seed and at each robustness level
HEADLINE_FIGURES = ("iou", "miou", "ciou")


def scored(conf: np.ndarray, *, n_boot: int, seed: int) -> dict:
    """A table row of (seeds, scenarios, K, K) confusions: every figure's interval, and IoU, mIoU and
    cIoU of each seed."""
    return {"figures": intervals(conf, n_boot=n_boot, seed=seed),
            "per_seed": {f: [round(figure_of(ssc_scores(c.sum(0)), f), 6) for c in conf] for f in HEADLINE_FIGURES}}


def ratio_interval(num: np.ndarray, den: np.ndarray, figure: str, *, n_boot: int, seed: int = 0) -> dict[str, float]:
    """``figure`` of ``num``'s networks over ``figure`` of ``den``'s (each the mean over seeds of the
    figure pooled over scenarios), from (seeds, scenarios, K, K) confusion matrices of the same test
    scenarios and training seeds: both are resampled together (paired), seed k of each side drawn
    as one (modulo its seed count)."""
    num, den = np.asarray(num), np.asarray(den)
    if num.shape[1:] != den.shape[1:]:
        raise TypError("tasks.ssc.ratio_interval", "den", f"matrices of the same scenarios as num {num.shape[1:]}",
                       den.shape[1:])
    n_seeds = max(len(num), len(den))

    def stat(c: np.ndarray, s: np.ndarray) -> float:
        a = np.mean([figure_of(ssc_scores(num[k % len(num)][c].sum(0)), figure) for k in s])
        b = np.mean([figure_of(ssc_scores(den[k % len(den)][c].sum(0)), figure) for k in s])
        return float(a / b) if b > 0 else float("nan")

    return bootstrap(stat, num.shape[1], n_seeds, n_boot=n_boot, seed=seed).to_dict()


# ---------------------------------------------------------------- the stage


def run(block: SscConfig, root: Path, *, log: Callable[[str], None] = print,
        log_fn: Callable[[dict, int | None], None] | None = None) -> dict:
    """Train every seed's networks, score Table I (perfect and noisy), the networks trained on
    generated cooperators against the oracle ones, and the robustness sweeps; returns the results
    the report and the metrics are made of."""
    sim = Path(root) / block.sim / block.domain
    out = Path(root) / block.out
    test_ds = ssc_dataset(sim / block.test_split, comm_range=block.comm_range)
    data = training_set(block, root, "oracle")
    weights = class_weights(data.class_counts(), eps=block.class_weight_eps)
    skipped: dict[str, str] = {}
    # why the generated arm cannot run (None: it runs), asked once for training and for scoring
    gen_unavailable = unavailable(generated_root(block, root)) if "generated" in block.data else None
    generated = "generated" in block.data and gen_unavailable is None
    train_arms(block, root, ["oracle", "generated"] if generated else ["oracle"], weights, log)
    noisy_ds = test_ds.with_options(position_std=block.noisy.position_std,
                                    heading_std_deg=block.noisy.heading_std_deg,
                                    delay_frames=block.noisy.delay_ms // 100, seed=block.seed)
    trained = [train_seed(block, data, weights, seed, out, log) for seed in block.training_seeds]
    losses = {f"oracle/{n}-seed{t.seed}": t.losses[n] for t in trained for n in t.losses}
    for nets in trained:
        if log_fn is not None:
            for name, curve in nets.losses.items():
                if curve:
                    log_fn({f"loss_{name}_seed{nets.seed}_last": float(np.mean(curve[-20:]))}, None)
    tables: dict[str, dict] = {}
    perfect: dict[str, np.ndarray] = {}     # the oracle networks' confusions, for the generated ratios
    for setting, ds in (("perfect", test_ds), ("noisy", noisy_ds)):
        rows = {}
        for method in block.methods:
            per_seed = [confusions(nets, ds, method) for nets in trained]
            conf = np.stack([c for c, _ in per_seed])
            if setting == "perfect":
                perfect[method] = conf
            rows[method] = {**scored(conf, n_boot=block.bootstrap, seed=block.seed), **per_seed[0][1]}
        tables[setting] = rows
    if "generated" in block.data:   # TYP Table 1 for SSC: the cooperating clouds of training generated
        if generated:
            gen = training_set(block, root, "generated")
            gen_trained = [train_seed(block, gen, weights, seed, out, log, data_name="generated")
                           for seed in block.training_seeds]
            losses.update({f"generated/{n}-seed{t.seed}": t.losses[n] for t in gen_trained for n in t.losses})
            rows = {}
            for method in block.methods:
                if method == "none":      # the ego's cloud is never generated: no fusion is the oracle row
                    continue
                conf = np.stack([confusions(nets, test_ds, method)[0] for nets in gen_trained])
                oracle = perfect[method]
                boot = dict(n_boot=block.bootstrap, seed=block.seed)
                rows[method] = {**scored(conf, **boot), "ratio_miou": ratio_interval(conf, oracle, "miou", **boot),
                                "ratio_iou": ratio_interval(conf, oracle, "iou", **boot), "frames": len(test_ds)}
            tables["generated"] = rows
        else:
            skipped["generated"] = gen_unavailable
            log(f"ssc: the generated rows are skipped: {gen_unavailable}")
    robustness = robustness_curves(block, trained[0], test_ds)
    sample = test_ds[0]     # the gallery: the first test frame by every method, first seed
    gallery = (ego_map(test_ds, 0, sample), {m: predict(trained[0], sample, m) for m in block.methods},
               f"{sample.scenario} frame {sample.timestamp}, ego {sample.agent_ids[0]}, "
               f"{len(sample.agent_ids) - 1} cooperating agent(s); seed {trained[0].seed}")
    return {"tables": tables, "robustness": robustness, "skipped": skipped, "gallery": gallery,
            "class_weights": dict(zip(SSC_CLASSES, weights.round(4).tolist())),
            "train": {"samples": len(data.samples), "views": len(data.views),
                      "scenarios": len({s.scenario for s in data.samples})},
            "test": {"samples": len(test_ds), "scenarios": len(test_ds.scenarios)},
            "seeds": list(block.training_seeds), "losses": losses, "networks": trained}


def robustness_curves(block: SscConfig, nets: SscNetworks, test_ds: FusionDataset) -> dict:
    """mIoU / IoU of every method against pose noise, delay and (AttFuse, V2X-ViT) message bits, first seed, on
    the test frames t >= the longest delay; each level a bootstrap interval over scenarios (no fusion:
    the reference, unperturbed)."""
    rob = block.robustness
    methods = list(block.methods)
    max_delay = max(rob.delay_ms, default=0) // 100
    # every sweep on the same frames, t >= the longest delay (the delays need them; the zero level
    # of each sweep is then one score, and the sweeps cost a quarter of tiny's test frames)
    frames = test_ds.with_options(first_frame=max_delay)
    sweeps = {"position_std": [dict(position_std=v) for v in rob.position_std],
              "heading_std_deg": [dict(heading_std_deg=v) for v in rob.heading_std_deg],
              "delay_ms": [dict(delay_frames=v // 100) for v in rob.delay_ms]}
    levels = {"position_std": list(rob.position_std), "heading_std_deg": list(rob.heading_std_deg),
              "delay_ms": list(rob.delay_ms)}
    curves: dict[str, dict] = {m: {} for m in methods}
    applied = {}
    cache: dict[tuple, dict] = {}
    for sweep, options in sweeps.items():
        for method in methods:
            cells = []
            for opt in options:
                ds = frames.with_options(seed=block.seed, **opt)
                # no fusion never reads a cooperating agent, and a zero level is no perturbation
                level = tuple(sorted((n, v) for n, v in opt.items() if v))
                k = (method, level if method != "none" else ())
                if k not in cache:
                    conf, info = confusions(nets, ds, method)
                    cache[k] = {**intervals(conf, n_boot=block.bootstrap, seed=block.seed, figures=HEADLINE_FIGURES),
                                **info}
                cells.append(cache[k])
            curves[method][sweep] = cells
            if sweep == "delay_ms" and method != "none":
                applied = [c["applied_delay_ms"] for c in cells]
    bits: dict[str, dict] = {}
    for method in methods:          # the methods whose cooperating agents send features
        if get_method(method).message == "features":
            bits[method] = {}
            for b in rob.quantization_bits:
                conf, info = confusions(nets, frames, method, bits=b)
                bits[method][str(b)] = {**intervals(conf, n_boot=block.bootstrap, seed=block.seed,
                                                    figures=HEADLINE_FIGURES), **info}
    return {"levels": levels, "methods": curves, "applied_delay_ms": applied or list(map(float, rob.delay_ms)),
            "quantization": bits}


def metrics_of(results: dict, seconds: float) -> dict:
    """metrics/ssc.json: Table I's figures with intervals, the robustness curves' mIoU, the sizes."""
    tables = {setting: {m: {**row["figures"], "per_seed": row["per_seed"], "frames": row["frames"]}
                        for m, row in rows.items()} for setting, rows in results["tables"].items()}
    perfect = results["tables"]["perfect"]
    targets = {}
    if "none" in perfect:
        none = perfect["none"]["figures"]
        targets["none_iou_ge_0.50"] = none["iou"]["value"] >= 0.50
        targets["none_miou_ge_0.35"] = none["miou"]["value"] >= 0.35
        for m, row in perfect.items():
            if m != "none":
                f = row["figures"]
                targets[f"{m}_beats_none_iou"] = f["iou"]["low"] > none["iou"]["high"]
                targets[f"{m}_beats_none_miou"] = f["miou"]["low"] > none["miou"]["high"]
    for m, row in results["tables"].get("generated", {}).items():
        targets[f"{m}_generated_ge_0.85_oracle_miou"] = row["ratio_miou"]["value"] >= 0.85
        tables["generated"][m].update(ratio_miou=row["ratio_miou"], ratio_iou=row["ratio_iou"])
    rob = results["robustness"]
    curves = {m: {sweep: [c["miou"]["value"] for c in cells] for sweep, cells in entry.items()}
              for m, entry in rob["methods"].items()}
    return {"tables": tables, "targets": targets, "robustness_miou": curves, "levels": rob["levels"],
            "applied_delay_ms": rob["applied_delay_ms"],
            "quantization_miou": {m: {b: v["miou"]["value"] for b, v in per.items()}
                                  for m, per in rob["quantization"].items()},
            "class_weights": results["class_weights"], "train": results["train"], "test": results["test"],
            "skipped": results["skipped"],
            "seeds": results["seeds"], "seconds_total": round(seconds, 3)}

