"""Stage ``simulate``: each domain's scenarios in OPV2V layout, from the embedded simulator or
from a real dataset (``simulate.sources``).

Output: ``<out>/<domain>/<split>/<scenario>/<agent_id>/<timestamp>.pcd|.yaml`` (OPV2V layout,
the ego is the first agent id in sorted order), beside them the semantic occupancy ground
truth ``<timestamp>_semantic_occupancy.npz`` of each view of the domains in
``simulate.occupancy`` (:mod:`typ.ssc`; real datasets bring their own or none), plus
``<scenario>/_typ.json``, the scenario's job key. A real dataset's scenarios (the first
``scenarios[domain][split]`` of each split, by name, its sources in order) are checked before
anything is written (:func:`plan_jobs`:
layout, yaml keys, pose format, agents, every frame of a single-agent dataset; the first bad
file is named). An OPV2V-layout scenario's ``.pcd``/``.yaml`` files are hard-linked into the
output (copied across file systems); a KITTI / nuScenes / Waymo scenario is written as a
one-agent scenario in its LiDAR's frame (:mod:`tasks.ingest`), so the later stages read them as
they read simulated ones. A scenario whose key is unchanged is skipped (an OPV2V-layout one's
key: its files' names, sizes and modification times; a single-agent one's: its files' content);
each scenario is written to a temporary folder and renamed into place, so a killed run leaves
only whole scenarios. Which dataset split went to which of typ's, and by what rule, is in the
metrics (``splits``).
"""
from __future__ import annotations

import dataclasses
import hashlib
import os
import shutil
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from typ import __version__
from tasks.ingest import IngestJob, source_splits
from tasks.scene_stage import SceneStage
from typ.config import Config, SimulateConfig, SourceConfig, as_dict
from typ.errors import TypError
from typ.formats.opv2v import check_root, check_scenario, list_agents, write_scene
from typ.io import SCENARIO_MANIFEST, atomic_path, code_digest, hash_obj, hidden_below, read_json_or_none, write_manifest
import typ.formats.opv2v
import typ.formats.pcd
import typ.geometry
import typ.sim
from typ.sim import simulate_scenario
from typ.ssc import occupancy_path, scene_occupancy, write_occupancy
import typ.ssc
from typ.registry import declare

STAGE = "simulate"
#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare("simulate", outs=("data/sim",))
MANIFEST = SCENARIO_MANIFEST
#: the simulator's and the writer's source: a change to either redoes every scenario
_CODE = code_digest(typ.sim, typ.geometry, typ.formats.opv2v, typ.formats.pcd, typ.ssc)


@dataclass(frozen=True)
class ScenarioJob:
    """One scenario to simulate: where it goes and everything that determines its content."""

    domain: str
    split: str
    index: int
    seed: int
    n_agents: int
    n_frames: int
    azimuth_step_deg: float
    comm_range: float
    dt: float
    #: also write each view's semantic occupancy ground truth (``SimulateConfig.occupancy``)
    occupancy: bool = True

    @property
    def name(self) -> str:
        return f"{self.domain}_{self.split}_{self.index:04d}"

    def folder(self, out: Path) -> Path:
        return out / self.domain / self.split / self.name

    def key(self) -> str:
        return hash_obj({"job": as_dict(self.__dict__), "code": _CODE})

    def describe(self) -> dict:
        return as_dict(self.__dict__)

    def write(self, tmp: Path) -> dict:
        """Simulate the scenario into ``tmp``; its counts."""
        scenes = simulate_scenario(domain=self.domain, seed=self.seed, n_frames=self.n_frames,
                                   n_agents=self.n_agents, azimuth_step_deg=self.azimuth_step_deg,
                                   comm_range=self.comm_range, dt=self.dt, scenario=self.name, split=self.split)
        maps = (scene_occupancy(domain=self.domain, seed=self.seed, n_frames=self.n_frames, n_agents=self.n_agents,
                                comm_range=self.comm_range, dt=self.dt) if self.occupancy else [None] * len(scenes))
        for scene, frame_maps in zip(scenes, maps):
            # write_scene writes into a folder named like the scenario: name it after tmp
            write_scene(dataclasses.replace(scene, scenario=tmp.name), tmp)
            for agent, labels in zip(scene.agents, frame_maps or ()):
                write_occupancy(occupancy_path(tmp, agent, scene.timestamp), labels)
        return {"frames": len(scenes), "views": sum(len(s.agents) for s in scenes),
                "points": int(sum(len(a.points) for s in scenes for a in s.agents.values())),
                "boxes": int(sum(len(a.boxes) for s in scenes for a in s.agents.values()))}


#: the files of a real scenario that typ reads (camera images and other sidecars stay where they are)
REAL_SUFFIXES = (".pcd", ".yaml")


@dataclass(frozen=True)
class ImportJob:
    """One scenario of a real OPV2V-layout dataset, taken into the output as it is."""

    domain: str
    split: str
    source: Path
    #: frames, views, points, boxes, from :func:`typ.formats.opv2v.check_scenario` when planned
    counts: dict = field(default_factory=dict, compare=False, hash=False)

    @property
    def name(self) -> str:
        return self.source.name

    @property
    def rule(self) -> str:
        """How the scenario came to its split (the stage's metrics)."""
        return f"opv2v folder {self.source.parent.name}"

    def folder(self, out: Path) -> Path:
        return out / self.domain / self.split / self.name

    def files(self) -> list[Path]:
        """The agents' ``.pcd`` and ``.yaml`` files, sorted."""
        return sorted(f for agent in list_agents(self.source) for f in (self.source / agent).iterdir()
                      if f.is_file() and f.suffix in REAL_SUFFIXES and not f.name.startswith("."))

    def key(self) -> str:
        stats = [(str(f.relative_to(self.source)), f.stat().st_size, f.stat().st_mtime_ns) for f in self.files()]
        return hash_obj({"source": str(self.source.resolve()), "files": stats, "code": _IMPORT_CODE})

    def describe(self) -> dict:
        return {"domain": self.domain, "split": self.split, "source": str(self.source.resolve())}

    def check(self) -> dict:
        """The scenario checked (:func:`typ.formats.opv2v.check_scenario`): its counts."""
        return check_scenario(self.source)

    def write(self, tmp: Path) -> dict:
        """Hard-link (else copy) the scenario's files into ``tmp``; its counts."""
        counts = self.counts or check_scenario(self.source)
        for f in self.files():
            target = tmp / f.relative_to(self.source)
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.link(f, target)
            except OSError:  # another file system, or links not allowed there
                shutil.copy2(f, target)
        return dict(counts)


#: what decides how a real scenario is checked and laid out
_IMPORT_CODE = code_digest(typ.formats.opv2v, typ.formats.pcd)


def plan_jobs(cfg: SimulateConfig, *, root: Path = Path("."), out: Path | None = None,
              where: str = "params.yaml") -> list:
    """All scenarios the config asks for: :class:`ScenarioJob` per simulated scenario, each with its
    own seed derived from ``cfg.seed``, :class:`ImportJob` per scenario of a real OPV2V-layout
    dataset and :class:`tasks.ingest.IngestJob` per scenario of a KITTI / nuScenes / Waymo one.

    A simulated scenario's seed depends only on (seed, domain, split, index), so adding scenarios
    to a split leaves the existing ones byte-identical and DVC/our keys skip them. A real
    dataset's root (relative to ``root``) is checked here, before anything is written: its
    splits, and every scenario not already taken unchanged into ``out`` (the first bad file
    raises TypError naming it; a split asked for more scenarios than it has names ``where``).
    """
    jobs = []
    for domain in sorted(cfg.scenarios):
        if cfg.source_blocks(domain):
            jobs += _real_jobs(cfg, domain, root, out, where)
            continue
        for split in sorted(cfg.scenarios[domain]):
            for index in range(cfg.scenarios[domain][split]):
                tag = int.from_bytes(hashlib.sha256(f"{domain}/{split}".encode()).digest()[:4], "little")
                ss = np.random.SeedSequence([cfg.seed, tag, index])
                seed = int(ss.generate_state(1, np.uint32)[0])
                frames, agents_min, agents_max = cfg.for_domain(domain)
                n_agents = int(np.random.default_rng(ss).integers(agents_min, agents_max + 1))
                jobs.append(ScenarioJob(domain, split, index, seed, n_agents, frames,
                                        cfg.azimuth_step_deg, cfg.comm_range, cfg.dt,
                                        occupancy=domain in cfg.occupancy))
    return jobs


def _real_jobs(cfg: SimulateConfig, domain: str, root: Path, out: Path | None, where: str) -> list:
    """The first ``scenarios[domain][split]`` scenarios each split takes from the domain's sources,
    every one not already taken unchanged into ``out`` checked now."""
    wanted = {split: n for split, n in sorted(cfg.scenarios[domain].items()) if n > 0}
    found: dict[str, list] = {split: [] for split in wanted}
    for index, block in enumerate(cfg.source_blocks(domain)):
        for split, jobs in _source_jobs(block, domain, list(wanted), root / block.root, where,
                                        cfg.source_field(domain, index)).items():
            found.get(split, []).extend(jobs)
    twice = [name for name, k in Counter(job.name for jobs in found.values() for job in jobs).items() if k > 1]
    if twice:   # one scenario in two splits, or two datasets' scenarios of one name
        raise TypError(where, f"simulate.sources.{domain}", "sources whose scenarios have distinct names",
                       f"{twice[0]} twice")
    jobs = []
    for split, n in wanted.items():
        if len(found[split]) < n:
            raise TypError(where, f"simulate.scenarios.{domain}.{split}",
                           f"at most {len(found[split])} (the scenarios its sources give it)", n)
        for job in found[split][:n]:
            manifest = read_json_or_none(job.folder(out) / MANIFEST) if out is not None else None
            if manifest is None or manifest.get("key") != job.key():   # new or changed: check it now
                job = dataclasses.replace(job, counts=job.check())
            jobs.append(job)
    return jobs


def _source_jobs(block: SourceConfig, domain: str, splits: list[str], data_root: Path, where: str,
                 field: str) -> dict[str, list]:
    """typ split -> the jobs of one source, its scenarios sorted by name."""
    if block.format != "opv2v":
        shares = source_splits(block, data_root, where=where, field=field)
        return {split: [IngestJob(domain, split, s, rule=share.rule) for s in share.scenarios]
                for split, share in shares.items()}
    folders = {split: block.splits.get(split, []) if block.splits else [split] for split in splits}
    found = check_root(data_root, sorted({f for names in folders.values() for f in names}))
    return {split: sorted((ImportJob(domain, split, s) for f in names for s in found[f]), key=lambda job: job.name)
            for split, names in folders.items()}


def split_rules(jobs: list) -> dict:
    """domain -> split -> how the real scenarios taken into it were chosen (the stage's metrics)."""
    rules: dict = {}
    for job in jobs:
        if not isinstance(job, ScenarioJob):
            rules.setdefault(job.domain, {}).setdefault(job.split, set()).add(job.rule)
    return {domain: {split: sorted(r) for split, r in sorted(splits.items())}
            for domain, splits in sorted(rules.items())}


def stale_scenarios(jobs: list, out: Path) -> list[Path]:
    """What lies where scenario folders go (``<out>/<domain>/<split>/``) that no job produces (a
    split shrank, or someone else's files): the stage deletes those it wrote."""
    wanted = {job.folder(out) for job in jobs}
    return sorted(p for p in out.glob("*/*/*")   # hidden names: temporaries, typ's records (<domain>/.typ/)
                  if p not in wanted and not hidden_below(p, out))


def _job_state(job: ScenarioJob | ImportJob | IngestJob, out: Path) -> tuple[Path, str, dict, dict | None]:
    """(output folder, key, result fields, the skipped result when the stored scenario has the key)."""
    folder, key = job.folder(out), job.key()
    base = {"scenario": job.name, "domain": job.domain, "split": job.split,
            "imported": not isinstance(job, ScenarioJob)}
    manifest = read_json_or_none(folder / MANIFEST)
    done = {**base, "skipped": "unchanged", **manifest["counts"]} if manifest and manifest.get("key") == key else None
    return folder, key, base, done


def unchanged(job: ScenarioJob | ImportJob | IngestJob, *, out: Path) -> dict | None:
    """The skipped result of a scenario already written with this job's key, else None."""
    return _job_state(job, out)[3]


def run_job(job: ScenarioJob | ImportJob | IngestJob, out: Path) -> dict:
    """Simulate or take one scenario and write it; returns counts, or ``skipped`` with the reason."""
    folder, key, base, done = _job_state(job, out)
    if done is not None:
        return done
    t0 = time.perf_counter()
    with atomic_path(folder, stage=STAGE, inside=out) as tmp:
        tmp.mkdir(parents=True)
        counts = job.write(tmp)
        write_manifest(tmp, STAGE, {"key": key, "job": job.describe(), "counts": counts, "typ_version": __version__})
    return {**base, "skipped": None, "seconds": time.perf_counter() - t0, **counts}


def summarize(results: list[dict]) -> dict:
    """Stage metrics: per domain/split counts plus totals and timings."""
    metrics: dict = {"scenarios": len(results),
                     "simulated": sum(r["skipped"] is None and not r.get("imported") for r in results),
                     "imported": sum(r["skipped"] is None and bool(r.get("imported")) for r in results),
                     "skipped_unchanged": sum(r["skipped"] == "unchanged" for r in results),
                     "seconds_simulating": round(sum(r.get("seconds", 0.0) for r in results), 3)}
    for r in results:
        group = metrics.setdefault(f"{r['domain']}_{r['split']}", {"scenarios": 0, "frames": 0, "views": 0,
                                                                  "points": 0, "boxes": 0})
        group["scenarios"] += 1
        for k in ("frames", "views", "points", "boxes"):
            group[k] += r[k]
    for k, group in metrics.items():
        if isinstance(group, dict) and group["views"]:
            group["points_per_view"] = round(group["points"] / group["views"], 1)
    return metrics


def scene_stage(cfg: Config, root: Path) -> SceneStage:
    """The stage's pieces for ``flows.common``. A real dataset's folders are checked here, before
    the stage's run starts or writes anything."""
    out = root / cfg.simulate.out
    jobs = plan_jobs(cfg.simulate, root=root, out=out, where=cfg.source)
    rules = split_rules(jobs)
    return SceneStage(out=out, plan=lambda: (jobs, stale_scenarios(jobs, out)),
                      work=run_job, work_kwargs={"out": out},
                      label=lambda job: job.name,
                      summarize=lambda results: {**summarize(results), **({"splits": rules} if rules else {})},
                      unchanged=unchanged)
