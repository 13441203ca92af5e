"""Stage ``simulate``: write the embedded simulator's scenarios in OPV2V layout.

Output: ``<out>/<domain>/<split>/<scenario>/<agent_id>/<timestamp>.pcd|.yaml`` (OPV2V layout,
the ego is the first agent id in sorted order) plus ``<scenario>/_typ.json``, the scenario's
job key. A scenario whose key is unchanged is skipped; each scenario is written to a
temporary folder and renamed into place, so a killed run leaves only whole scenarios.
"""
from __future__ import annotations

import dataclasses
import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from typ import __version__
from typ.config import SimulateConfig, as_dict
from typ.formats.opv2v import write_scene
from typ.io import atomic_path, code_digest, hash_obj, read_json_or_none, write_json
import typ.formats.opv2v
import typ.formats.pcd
import typ.geometry
import typ.sim
from typ.sim import simulate_scenario

MANIFEST = "_typ.json"
#: the simulator's and the writer's source: a change to either redoes every scenario
_CODE = code_digest(typ.sim, typ.geometry, typ.formats.opv2v, typ.formats.pcd)


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

    @property
    def name(self) -> str:
        return f"{self.domain}_{self.split}_{self.index:04d}"

    def folder(self, out: Path) -> Path:
        return out / self.domain / self.split / self.name

    def key(self) -> str:
        return hash_obj({"job": as_dict(self.__dict__), "code": _CODE})


def plan_jobs(cfg: SimulateConfig) -> list[ScenarioJob]:
    """All scenarios the config asks for, each with its own seed derived from ``cfg.seed``.

    A scenario's seed depends only on (seed, domain, split, index), so adding scenarios to a
    split leaves the existing ones byte-identical and DVC/our keys skip them.
    """
    jobs = []
    for domain in sorted(cfg.scenarios):
        for split in sorted(cfg.scenarios[domain]):
            for index in range(cfg.scenarios[domain][split]):
                tag = int.from_bytes(hashlib.sha256(f"{domain}/{split}".encode()).digest()[:4], "little")
                ss = np.random.SeedSequence([cfg.seed, tag, index])
                seed = int(ss.generate_state(1, np.uint32)[0])
                frames, agents_min, agents_max = cfg.for_domain(domain)
                n_agents = int(np.random.default_rng(ss).integers(agents_min, agents_max + 1))
                jobs.append(ScenarioJob(domain, split, index, seed, n_agents, frames,
                                        cfg.azimuth_step_deg, cfg.comm_range, cfg.dt))
    return jobs


def stale_scenarios(jobs: list[ScenarioJob], out: Path) -> list[Path]:
    """Scenario folders on disk that no job produces any more (a split shrank)."""
    wanted = {job.folder(out) for job in jobs}
    return sorted(p for p in out.glob("*/*/*") if p.is_dir() and p not in wanted and not p.name.startswith("."))


def run_job(job: ScenarioJob, out: Path) -> dict:
    """Simulate one scenario and write it; returns counts, or ``skipped`` with the reason."""
    folder = job.folder(out)
    manifest = read_json_or_none(folder / MANIFEST)
    if manifest is not None and manifest.get("key") == job.key():
        return {"scenario": job.name, "domain": job.domain, "split": job.split, "skipped": "unchanged",
                **manifest["counts"]}
    t0 = time.perf_counter()
    scenes = simulate_scenario(domain=job.domain, seed=job.seed, n_frames=job.n_frames, n_agents=job.n_agents,
                               azimuth_step_deg=job.azimuth_step_deg, comm_range=job.comm_range, dt=job.dt,
                               scenario=job.name, split=job.split)
    counts = {"frames": len(scenes), "views": sum(len(s.agents) for s in scenes),
              "points": int(sum(len(a.points) for s in scenes for a in s.agents.values())),
              "boxes": int(sum(len(a.boxes) for s in scenes for a in s.agents.values()))}
    with atomic_path(folder) as tmp:
        tmp.mkdir(parents=True)
        for scene in scenes:
            # write_scene writes into a folder named like the scenario: name it after tmp
            write_scene(dataclasses.replace(scene, scenario=tmp.name), tmp)
        write_json(tmp / MANIFEST, {"key": job.key(), "job": as_dict(job.__dict__), "counts": counts,
                                    "typ_version": __version__})
    return {"scenario": job.name, "domain": job.domain, "split": job.split, "skipped": None,
            "seconds": time.perf_counter() - t0, **counts}


def summarize(results: list[dict]) -> dict:
    """Stage metrics: per domain/split counts plus totals and timings."""
    metrics: dict = {"scenarios": len(results),
                     "simulated": sum(r["skipped"] is None for r in results),
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
