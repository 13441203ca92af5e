"""Training of stage ``ssc`` (module :mod:`tasks.ssc`): the single-agent network and the fused ones
warm-started from it, on the shared resumable loop, each saved with the key of what it learned
from; the (data, seed) arms on spawned one-thread processes."""
from __future__ import annotations

import copy
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from models.fusion import FusionModule, NoFusion, build, get_method, merge_agent_points
from models.pointpillars import PointPillars
from models.ssc import ssc_detector
from tasks.fusion_data import FusionSample
from tasks.ssc_data import IGNORE, NETWORK, STAGE, TrainingSet, model_kwargs, ssc_dataset
from tasks.training import (Trainings, drop_checkpoints, learning_rate, one_thread, run_checkpoint_dir, run_loop,
                            seed_everything, set_learning_rate)
from typ import distributed
from typ.artifacts import load_if_key, save_module
from typ.config import SscConfig
from typ.errors import TypError
from typ.io import hash_obj, seed_dir


def _fit(model: FusionModule, step: Callable[[int, torch.device], tuple[torch.Tensor, np.ndarray]], n_items: int, *,
         steps: int, seed: int, lr: float, weights: np.ndarray, name: str, checkpoints: Path | None,
         checkpoint_every: int | None) -> list[float]:
    """``steps`` Adam steps (cosine decay to 0, :func:`tasks.training.learning_rate`) of
    class-weighted cross-entropy, item ``k`` of a seeded order each (every item once before any
    twice); ``step(k, device)`` -> (logits (1, K, X, Y, Z), labels), the inputs on ``device``. On
    the shared loop (:func:`tasks.training.run_loop`): checkpoints every ``checkpoint_every`` steps
    (None: at the end) in ``checkpoints`` (None: a temporary folder, no resume), a killed run resumes from the newest
    and ends with the bytes of an uninterrupted one. The model trains on the runtime device under
    its autocast precision and ends where it was. Returns every step's loss."""
    if checkpoints is None:
        with tempfile.TemporaryDirectory(prefix=".tmp-ssc-") as tmp:
            return _fit(model, step, n_items, steps=steps, seed=seed, lr=lr, weights=weights, name=name,
                        checkpoints=Path(tmp), checkpoint_every=checkpoint_every)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    order = np.random.default_rng(seed).permutation(np.resize(np.arange(n_items), steps))
    with distributed.on_device(model) as dev:
        w = torch.tensor(weights, dtype=torch.float32, device=dev)
        model.train()

        def step_fn(n: int) -> dict[str, float]:
            set_learning_rate(opt, learning_rate(lr, n, steps))
            logits, labels = step(int(order[n]), dev)
            labels = torch.as_tensor(labels, dtype=torch.long).to(dev)[None]
            loss = F.cross_entropy(logits.float(), labels, weight=w, ignore_index=IGNORE)
            opt.zero_grad()
            loss.backward()
            opt.step()
            return {"loss": loss.item()}

        result = run_loop(name=f"ssc {name}", total_steps=steps, step_fn=step_fn,
                          state={"model": model, "opt": opt},
                          checkpoint_dir=checkpoints, checkpoint_every=checkpoint_every or steps)
    model.eval()
    return [h["loss"] for h in result.history]


def _on(tensors: dict, device: torch.device) -> dict:
    """Every tensor of ``tensors`` on ``device`` (other values as they are)."""
    return {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in tensors.items()}


def train_single(data: TrainingSet, *, steps: int, seed: int, lr: float, model_kw: dict, weights: np.ndarray,
                 checkpoints: Path | None = None, checkpoint_every: int | None = None) -> tuple[NoFusion, list[float]]:
    """The single-agent network, one agent view (its own cloud, its own map) a step; resumable
    from ``checkpoints`` (:func:`_fit`)."""
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise TypError("tasks.ssc.train_single", "steps", "an integer >= 1", steps)
    seed_everything(seed)
    det = ssc_detector(**model_kw)
    model = NoFusion(detector=det)
    one = torch.ones(1, 1, dtype=torch.bool)

    def step(k: int, dev: torch.device):
        cloud, labels = data.views[k]
        return model(_on(det.pillarize([cloud]), dev), agent_mask=one.to(dev))["occ"], labels

    return model, _fit(model, step, len(data.views), steps=steps, seed=seed, lr=lr, weights=weights, name="single",
                       checkpoints=checkpoints, checkpoint_every=checkpoint_every)


def _inputs(det: PointPillars, method: str, sample: FusionSample) -> tuple[dict, dict]:
    """(pillars, forward keywords) of one sample for ``method``'s module (batch of one), pillarized by
    ``det`` (the single-agent network's detector: every network shares its pillar grid)."""
    if get_method(method).inputs == "merged":
        return det.pillarize([merge_agent_points(sample.clouds, sample.transforms)]), \
            {"agent_mask": torch.ones(1, 1, dtype=torch.bool)}
    n = len(sample.clouds)
    return det.pillarize(list(sample.clouds)), {
        "agent_mask": torch.ones(1, n, dtype=torch.bool),
        "transforms": torch.from_numpy(np.asarray(sample.transforms, dtype=np.float64))[None],
        "time_delay": torch.as_tensor(np.asarray(sample.time_delay), dtype=torch.long)[None]}


def train_fused(method: str, data: TrainingSet, single: NoFusion, *, steps: int, seed: int, lr: float,
                weights: np.ndarray, options: dict | None = None, checkpoints: Path | None = None,
                checkpoint_every: int | None = None) -> tuple[FusionModule, list[float]]:
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

    return module, _fit(module, step, len(data.samples), steps=steps, seed=seed, lr=lr, weights=weights, name=method,
                        checkpoints=checkpoints, checkpoint_every=checkpoint_every)


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
        folder = seed_dir(out / "models" / data_name / name, seed)
        loaded = load_if_key(folder, _build, STAGE, key)
        if loaded is not None:
            module, meta = loaded
            result.networks[name], result.losses[name] = module, list(meta.get("losses", []))
            log(f"ssc: {data_name} {name} seed {seed} loaded from {folder} "
                f"(key {key}: trained by a worker or an earlier run)")
        else:
            resume = {"checkpoints": run_checkpoint_dir(seed_dir(out / "checkpoints" / data_name / name, seed), key),
                      "checkpoint_every": block.checkpoint_every}
            with one_thread():
                if name == "single":
                    module, losses = train_single(data, steps=block.steps, seed=seed, lr=block.lr, model_kw=model_kw,
                                                  weights=weights, **resume)
                else:
                    module, losses = train_fused(name, data, result.networks["single"],
                                                 steps=block.warm_start_steps, seed=seed, lr=block.finetune_lr,
                                                 weights=weights, options=options[name], **resume)
            save_module(folder, module, _network_config(name, model_kw, options[name]), key=key, seed=seed,
                        losses=[round(v, 6) for v in losses])
            drop_checkpoints(resume["checkpoints"], up_to=out)   # the saved network is the resume point now
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
               log: Callable[[str], None] = print, trainings: Trainings = Trainings(),
               sets: dict[str, TrainingSet] | None = None) -> None:
    """Train (or find by key) every network of each arm in ``arms`` and each seed, the (arm, seed)
    pairs on spawned one-thread processes, as many at once as torch has threads (module doc), each
    reported to ``trainings`` as ``train-<arm>-seed<k>``; :func:`train_seed` then loads them. With
    one thread or one pair nothing is spawned: they train here, on one thread as well, from
    ``sets[arm]`` where the caller has read that arm's training set already."""
    import concurrent.futures
    import multiprocessing

    jobs = [(arm, seed) for seed in block.training_seeds for arm in arms]
    workers = min(len(jobs), torch.get_num_threads())
    names = {job: f"train-{job[0]}-seed{job[1]}" for job in jobs}
    if workers < 2:
        sets = dict(sets or {})
        for arm, seed in jobs:
            if arm not in sets:
                sets[arm] = training_set(block, root, arm)
            trainings.run(names[arm, seed], lambda: train_seed(
                block, sets[arm], weights, seed, Path(root) / block.out, log, data_name=arm))
        return
    ctx = multiprocessing.get_context("spawn")    # no fork of a process whose OpenMP pool runs
    with concurrent.futures.ProcessPoolExecutor(workers, mp_context=ctx) as pool:
        futures = []
        for arm, seed in jobs:
            futures.append(pool.submit(_train_arm, block, Path(root), arm, seed, weights))
            trainings.started(names[arm, seed], futures[-1])
        for future in futures:                    # a worker's error is raised here
            log(f"ssc: the networks of {future.result()} are trained")
