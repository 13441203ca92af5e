"""docs/extending.md, done as written: every extensible kind is added in a temporary copy of the
source tree by editing only the files its section names, and what consumes it runs on it.

One copy holds all the additions (each edit below is the doc's worked example, verbatim in
spirit: a new file or one entry inserted beside its kind); one fresh Python process imports the
copy and exercises each consumer, so the copy's modules are the ones imported, not this
process's. Each test reads its kind's part of that run and checks the files it took.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from repo_paths import REPO

ROOT = REPO
PACKAGES = ("typ", "tasks", "models", "pipelines", "flows", "cli")


def _insert(path: Path, anchor: str, text: str, *, after: bool = True) -> None:
    """Put ``text`` right after (or before) the one occurrence of ``anchor`` in ``path``."""
    source = path.read_text()
    assert source.count(anchor) == 1, f"{path}: the anchor {anchor!r} moved; update docs/extending.md and this test"
    at = source.index(anchor) + (len(anchor) if after else 0)
    path.write_text(source[:at] + text + source[at:])


def _new(path: Path, text: str) -> None:
    assert not path.exists(), path
    path.write_text(textwrap.dedent(text).lstrip())


# ------------------------------------------------------------------ the additions, one per kind
# Each returns the files it created or edited, relative to the copy.

def add_fusion_method(copy: Path) -> set[str]:
    _new(copy / "models/fusion/maxfuse.py", '''
        """Max fusion: per BEV cell, the element-wise max over the agents' warped features."""
        from __future__ import annotations

        import torch

        from models.fusion.attfuse import AttFuse


        class MaxFuse(AttFuse):
            """AttFuse's network and messages, the agents' features fused by a max instead of attention."""

            @staticmethod
            def attend(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
                return x.masked_fill(~mask[:, :, None], float("-inf")).amax(1).clamp_min(-1e30)
        ''')
    _insert(copy / "typ/registry.py", "                 options=\"v2xvit\", warm_start=True),\n",
            '    FusionMethod("maxfuse", "MaxFuse", "MaxFuse", inputs="agents", targets="fused", message="features",\n'
            '                 warm_start=True),\n')
    return {"models/fusion/maxfuse.py", "typ/registry.py"}


def add_sampler(copy: Path) -> set[str]:
    _insert(copy / "typ/registry.py", "SAMPLERS: dict[str, SamplerSpec] = {\n",
            '    "euler": SamplerSpec("EulerDiscreteScheduler", {}, {}),\n')
    return {"typ/registry.py"}


def add_schedule(copy: Path) -> set[str]:
    _insert(copy / "models/schedules.py", "#: config name -> β(T), one function of this module per entry", '''\
def geometric(num_steps: int, *, beta_start: float = 1e-4, beta_end: float = 0.02) -> np.ndarray:
    """β rising geometrically from beta_start to beta_end."""
    return np.geomspace(beta_start, beta_end, num_steps)


''', after=False)
    _insert(copy / "typ/registry.py", '"hyperbolic", "time_dependent", "ramp"', ', "geometric"')
    return {"models/schedules.py", "typ/registry.py"}


def add_sensor_preset(copy: Path) -> set[str]:
    _insert(copy / "typ/sensors/presets.py", "PRESETS: dict[str, SensorSpec] = ", '''\
# a 16-beam LiDAR, 2 deg apart, on a 1.5 m mast (a worked example)
TOY = SensorSpec(name="toylidar", elevations_deg=tuple(float(e) for e in range(-15, 17, 2)), azimuth_step_deg=1.0,
                 max_range=60.0, min_range=0.5, mount_height=1.5, range_noise_std=0.0, dropout=0.0,
                 detection_energy=0.0, intensity_model="attenuation")

''', after=False)
    _insert(copy / "typ/sensors/presets.py", "V2V4REAL, OPV2V", ", TOY")
    return {"typ/sensors/presets.py"}


def add_reader(copy: Path) -> set[str]:
    _new(copy / "typ/formats/npyscan.py", '''
        """``npyscan``: ``<root>/<drive>/<frame>.npy`` scans, (N, 4) float32 [x, y, z, intensity] in the
        LiDAR's frame, no boxes, no poses (a worked example of a reader in one file)."""
        from __future__ import annotations

        from pathlib import Path

        import numpy as np

        from typ.errors import TypError
        from typ.inputs import inside
        from typ.scene import AgentView, Scene


        def read_npyscan_frame(path: Path) -> Scene:
            points = np.load(path, allow_pickle=False)
            if points.ndim != 2 or points.shape[1] != 4 or points.dtype != np.float32:
                raise TypError(path, "points", "(N, 4) float32 [x, y, z, intensity]", f"{points.shape} {points.dtype}")
            return Scene(path.parent.name, path.stem, {"ego": AgentView("ego", points, np.eye(4), where=str(path))})


        def find(root: Path):
            """Every drive folder holding .npy scans: (name, files, parts); no splits of its own."""
            scenarios = []
            for drive in sorted(p for p in root.iterdir() if p.is_dir()):
                files = [inside(p.relative_to(root), root) for p in sorted(drive.glob("*.npy"))]
                if files:
                    scenarios.append((f"npyscan_{drive.name}", files, tuple(files)))
            return scenarios, {}


        def frames(scenario):
            for path in scenario.parts:
                yield read_npyscan_frame(path)
        ''')
    _insert(copy / "typ/registry.py", "READERS: dict[str, ReaderSpec] = {\n",
            '    "npyscan": ReaderSpec("typ.formats.npyscan:find", "typ.formats.npyscan:frames",\n'
            '                          "<drive>/<frame>.npy scans", sensor="toylidar"),\n')
    return {"typ/formats/npyscan.py", "typ/registry.py"}


def add_compose_mode(copy: Path) -> set[str]:
    _insert(copy / "pipelines/typ/compose.py", "def composer(name: str)", '''\
def unseen(batch: Batch) -> list[np.ndarray]:
    """TYP's sample only in the cells the ego did not see."""
    from typ.resim import coverage_mask, in_mask

    return [c[~in_mask(c, coverage_mask(r.ego_points, batch.grid), batch.grid)]
            for c, r in zip(batch.clouds, batch.refs)]


''', after=False)
    _insert(copy / "typ/registry.py", "COMPOSE_MODES: dict[str, ComposeMode] = {\n",
            '    "unseen": ComposeMode("TYP\'s sample where the ego saw nothing", "pipelines.typ.compose:unseen"),\n')
    return {"pipelines/typ/compose.py", "typ/registry.py"}


def add_generation_figure(copy: Path) -> set[str]:
    _insert(copy / "tasks/genscore.py", "METRICS: dict[str, Metric] = {\n",
            '    "ground_ratio": Metric("ground voxels", lambda p: (int(p.occupancy[1].sum()), int(p.truth[1].sum())),\n'
            '                           pool_ratio, lower_is_better=True),\n')
    return {"tasks/genscore.py"}


def add_stage(copy: Path) -> set[str]:
    _new(copy / "tasks/density.py", '''
        """Stage ``density``: how many simulated scenes there are to score (a worked example)."""
        from __future__ import annotations

        from tasks.scene_stage import StageResult
        from typ.formats.opv2v import list_scenarios
        from typ.registry import declare

        DECLARATION = declare("density", data=("data/sim",), params=("simulate",))


        def run(cfg, root, *, run) -> StageResult:
            block = cfg.density
            scenes = list_scenarios(root / cfg.simulate.out / block.domain / block.split)
            return StageResult({"scenes": len(scenes)}, summary=f"# density\\n\\n{len(scenes)} scenes")
        ''')
    _insert(copy / "typ/registry.py", '    "evaluate": StageSpec("scoring"),\n',
            '    "density": StageSpec("scoring", torch=False),\n')
    _insert(copy / "typ/config/run.py", "@dataclass(frozen=True)\nclass Config:", '''\
@dataclass(frozen=True)
class DensityConfig:
    """Stage ``density``: the simulated split it counts."""

    domain: str = "target"
    split: str = "test"
    out: str = "reports/density"


''', after=False)
    _insert(copy / "typ/config/run.py", "    source: str = field(default=\"params.yaml\", compare=False)",
            "    density: DensityConfig = DensityConfig()\n", after=False)
    return {"tasks/density.py", "typ/registry.py", "typ/config/run.py"}


ADDITIONS = {"fusion method": add_fusion_method, "sampler": add_sampler, "schedule": add_schedule,
             "sensor preset": add_sensor_preset, "reader": add_reader, "compose mode": add_compose_mode,
             "generation figure": add_generation_figure, "stage": add_stage}

# ------------------------------------------------------------------ the consumers, in the copy

CONSUMERS = r'''
import json, sys, traceback
from pathlib import Path

import numpy as np

root, data = Path(sys.argv[1]), Path(sys.argv[2])
assert Path(__import__("typ").__file__).resolve().is_relative_to(root.resolve()), "imported the original tree"
out = {}


def kind(name):
    def wrap(fn):
        try:
            out[name] = fn()
        except Exception:
            out[name] = {"error": traceback.format_exc()}
    return wrap


from typ.config import config_from_dict


@kind("fusion method")
def _():
    import torch
    from models.fusion import build
    from models.pointpillars import PointPillars
    from typ.registry import METHODS

    torch.manual_seed(0)
    det = PointPillars(lidar_range=(-12.8, -6.4, -3.0, 12.8, 6.4, 1.0), voxel_size=0.4, pillar_channels=8,
                       layer_nums=(1, 1), layer_strides=(2, 2), num_filters=(8, 16), upsample_strides=(1, 2),
                       num_upsample_filters=(8, 8), max_pillars=2000)
    module = build("maxfuse", det)
    rng = np.random.default_rng(0)
    clouds = [np.c_[rng.uniform(-12, 12, 800), rng.uniform(-6, 6, 800), rng.uniform(-2.5, 0.5, 800),
                    rng.uniform(0, 1, 800)].astype(np.float32) for _ in range(2)]
    heads = module(det.pillarize(clouds), agent_mask=torch.ones(1, 2, dtype=torch.bool),
                   transforms=np.eye(4)[None, None].repeat(2, axis=1))
    cfg = config_from_dict({"profile": "tiny", "fusion": {"methods": ["none", "maxfuse"]},
                            "ssc": {"methods": ["none", "maxfuse"]}})
    # typ report: the new method's row in the one-page summary, after the registry's others
    evaluate = json.loads((root / "metrics" / "evaluate.json").read_text())
    table1 = evaluate["fusion"]["table1"]
    table1["maxfuse"] = table1["attfuse"]
    (root / "metrics" / "evaluate.json").write_text(json.dumps(evaluate))
    from typ.report import write_summary
    summary = write_summary(root).read_text()
    from flows import dvcyaml
    built = dvcyaml.build(root)
    return {"heads": sorted(heads), "finite": bool(all(torch.isfinite(v).all() for v in heads.values())),
            "config": list(cfg.fusion.methods), "ssc": list(cfg.ssc.methods), "last": list(METHODS)[-1],
            "summary_rows": [line.split("|")[1].strip() for line in summary.splitlines()
                             if line.startswith("| ") and line.split("|")[1].strip() in
                             ("No fusion", "Late", "AttFuse", "MaxFuse")],
            "plotted": "maxfuse" in json.dumps(built["plots"])}


@kind("sampler")
def _():
    import torch
    from models.samplers import make_scheduler
    from models.schedules import betas

    scheduler = make_scheduler("euler", betas("linear", 100))
    scheduler.set_timesteps(5)
    x = torch.randn(1, 2, 4, 4, generator=torch.Generator().manual_seed(0)) * scheduler.init_noise_sigma
    for t in scheduler.timesteps:
        x = scheduler.step(0.1 * scheduler.scale_model_input(x, t), t, x).prev_sample
    cfg = config_from_dict({"profile": "tiny", "stage1": {"sampler": "euler"}})
    return {"class": type(scheduler).__name__, "finite": bool(torch.isfinite(x).all()), "config": cfg.stage1.sampler}


@kind("schedule")
def _():
    from models.schedules import alphas_cumprod, betas

    b = betas("geometric", 50)
    cfg = config_from_dict({"profile": "tiny", "stage1": {"schedule": "geometric"}})
    return {"first": float(b[0]), "last": float(b[-1]), "rising": bool(np.all(np.diff(b) > 0)),
            "abar_falls": bool(np.all(np.diff(alphas_cumprod(b)) < 0)), "config": cfg.stage1.schedule}


@kind("sensor preset")
def _():
    from typ.castview import boxes_mesh
    from typ.sensors import resolve
    from typ.sim.raycast import cast_mesh

    spec = resolve("toylidar")
    verts, tris = boxes_mesh(np.array([[-30.0, -30.0, -spec.mount_height]]), np.array([[30.0, 30.0, 10.0]]))
    points = cast_mesh(verts, tris, spec)
    return {"rays": spec.n_beams * spec.n_azimuths, "returns": len(points), "height": spec.mount_height}


@kind("reader")
def _():
    from tasks.ingest import list_dataset, write_single_agent
    from typ.formats.opv2v import read_scene

    scenarios, splits = list_dataset("npyscan", data)
    written = write_single_agent(scenarios, root / "single_agent")
    first = written[0]
    cfg = config_from_dict({"profile": "tiny", "simulate": {"sources": {
        "target": {"format": "npyscan", "root": str(data)}}}})
    ego = read_scene(first, sorted(p.stem for p in (first / "ego").glob("*.pcd"))[0]).ego
    return {"scenarios": [s.name for s in scenarios], "lidar": scenarios[0].lidar, "frames": len(list(scenarios[0])),
            "written_points": int(len(ego.points)), "config": cfg.simulate.sources["target"].format}


@kind("compose mode")
def _():
    import dataclasses

    from pipelines.typ import reference_at
    from tiny_pipeline import TINY_GRID as grid, tiny_pipeline   # tests/helpers, on the copy's modules
    from typ.resim import coverage_mask, in_mask
    from typ.sim import simulate_scenario
    from typ.geometry import pose_to_matrix

    pipe = dataclasses.replace(tiny_pipeline(), thresholds={"low": 0.4, "high": 0.6, "noise_std": 0.0})
    ego = simulate_scenario(domain="target", seed=2, n_frames=1, n_agents=1)[0].ego
    g = grid.for_sensor(2.2)
    ref = reference_at(ego, ego.pose @ pose_to_matrix([8.0, -2.0, 0.0, 0.0, 150.0, 0.0]), "rsu", None, g)
    view, = pipe.generate([ref], g, seed=0, compose="unseen")
    everything, = pipe.generate([ref], g, seed=0, compose="generated")
    seen = coverage_mask(ref.ego_points, g)
    cfg = config_from_dict({"profile": "tiny", "generate": {"compose": "unseen"}})
    return {"points": len(view), "all": len(everything), "in_seen": int(in_mask(view, seen, g).sum()),
            "kept_unseen": bool(np.array_equal(view, everything[~in_mask(everything, seen, g)])),
            "config": cfg.generate.compose}


@kind("generation figure")
def _():
    from tasks import evaluate, genscore
    from typ.voxel import Grid

    grid = Grid((-12.8, 12.8), (-12.8, 12.8), (-0.75, 3.25), (64, 64, 8))
    truth = np.zeros((8, 64, 64), bool)
    truth[1] = True
    half = truth.copy()
    half[1, :, :32] = False
    stats = genscore.true_view_stats(truth, grid)
    rows = [[genscore.score_pair(v, np.zeros((0, 3)), truth, np.ones((64, 64), bool), np.zeros((0, 7)), grid, stats)
             for v in (truth, half)]]
    table = genscore.summarize(rows, ["a", "b"], [stats["histogram"]] * 2, [stats["centres"]] * 2, n_boot=50)
    md = evaluate.table({"typ": table}, evaluate.ACCURACY_COLUMNS)
    return {"pair": list(rows[0][1]["ground_ratio"]), "pooled": table["ground_ratio"].value,
            "column": "ground voxels" in md.splitlines()[0], "lower": genscore.lower_is_better("ground_ratio")}


@kind("stage")
def _():
    from flows import dvcyaml, pipeline
    from typ.config import Config

    built = dvcyaml.build(root)
    entry = built["stages"].get("density", {})
    return {"order": list(built["stages"])[-2:], "deps": entry.get("deps", []), "params": entry.get("params", []),
            "config": list(Config.STAGES)[-1], "flow": pipeline._flow("density").name,
            "block": config_from_dict({"profile": "tiny", "density": {"split": "train"}}).block("density").split}


print(json.dumps(out))
'''


@pytest.fixture(scope="module")
def extended(tmp_path_factory) -> tuple[dict, dict]:
    """(what each consumer gave, the files each kind's addition took) in one extended copy."""
    base = tmp_path_factory.mktemp("extended")
    copy = base / "project"
    for package in PACKAGES:
        shutil.copytree(ROOT / package, copy / package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "metrics", copy / "metrics")
    touched = {name: add(copy) for name, add in ADDITIONS.items()}
    drives = base / "npy"
    rng = np.random.default_rng(0)
    for drive in ("d0", "d1"):
        (drives / drive).mkdir(parents=True)
        for frame in range(2):
            cloud = np.c_[rng.uniform(-20, 20, (500, 2)), rng.uniform(-1.6, 0.5, 500), rng.uniform(0, 1, 500)]
            np.save(drives / drive / f"{frame:06d}.npy", cloud.astype(np.float32))
    done = subprocess.run([sys.executable, "-c", CONSUMERS, str(copy), str(drives)], cwd=copy, capture_output=True,
                          text=True, timeout=600, env={**__import__("os").environ,
                                                       "PYTHONPATH": f"{copy}:{ROOT / 'tests' / 'helpers'}"})
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1]), touched



#: files an addition may take: two, but a stage's config block still lives in typ/config/ (its own
#: file once a stage's config sits beside it)
MOST_FILES = {"stage": 3}


def _result(extended, kind: str) -> dict:
    got, touched = extended
    assert "error" not in got[kind], got[kind]["error"]
    assert len(touched[kind]) <= MOST_FILES.get(kind, 2), touched[kind]
    return got[kind]


def test_a_fusion_method_is_its_module_and_an_entry_and_reaches_the_config_ssc_dvc_yaml_and_typ_report(extended):
    r = _result(extended, "fusion method")
    assert r["heads"] == ["dm", "psm", "rm"] and r["finite"]
    assert r["config"] == ["none", "maxfuse"] and r["ssc"] == ["none", "maxfuse"] and r["last"] == "maxfuse"
    assert r["plotted"] and r["summary_rows"][:4] == ["No fusion", "Late", "AttFuse", "MaxFuse"]   # table 1, in order


def test_a_sampler_is_one_entry_that_builds_samples_and_configures(extended):
    r = _result(extended, "sampler")
    assert r == {"class": "EulerDiscreteScheduler", "finite": True, "config": "euler"}


def test_a_schedule_is_its_function_and_an_entry(extended):
    r = _result(extended, "schedule")
    assert r["first"] == pytest.approx(1e-4) and r["last"] == pytest.approx(0.02)
    assert r["rising"] and r["abar_falls"] and r["config"] == "geometric"


def test_a_sensor_preset_is_one_entry_that_resolves_and_casts(extended):
    r = _result(extended, "sensor preset")
    assert r["rays"] == 16 * 360 and r["height"] == 1.5
    assert r["returns"] == r["rays"]          # a closed room: every ray returns


def test_a_reader_is_its_format_module_and_an_entry_and_its_scans_are_written(extended):
    r = _result(extended, "reader")
    assert r["scenarios"] == ["npyscan_d0", "npyscan_d1"] and r["lidar"] == "toylidar" and r["frames"] == 2
    assert r["written_points"] == 500 and r["config"] == "npyscan"


def test_a_compose_mode_is_its_function_and_an_entry_that_generate_runs(extended):
    r = _result(extended, "compose mode")
    assert r["config"] == "unseen" and r["in_seen"] == 0 and r["kept_unseen"]
    assert 0 < r["points"] < r["all"]


def test_a_generation_figure_is_one_entry_scored_pooled_and_tabled(extended):
    r = _result(extended, "generation figure")
    assert r["pair"] == [32 * 64, 64 * 64] and r["pooled"] == pytest.approx(0.75)
    assert r["column"] and r["lower"]


def test_a_stage_is_its_task_module_and_an_entry_and_gets_its_dvc_stage_and_flow(extended):
    r = _result(extended, "stage")
    assert r["order"] == ["evaluate", "density"] and r["config"] == "density" and r["flow"] == "density"
    assert r["block"] == "train"
    assert "data/sim" in r["deps"] and "tasks/density.py" in r["deps"] and "simulate" in r["params"]
