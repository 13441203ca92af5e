"""dvc.yaml declares what each stage reads: every module its flow imports, and the profile keys
of every params block it reads, so that a change re-runs the stages it affects and no other."""
from __future__ import annotations

import pytest
import yaml

from dvc_deps import FOLDERS, ROOT, closure, code_deps
from dvc_params import profile_params

DVC = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]


@pytest.mark.parametrize("stage", sorted(DVC))
def test_code_deps_are_the_flows_import_closure(stage):
    deps = set(DVC[stage]["deps"])
    missing = [d for d in code_deps(stage) if d not in deps]
    assert not missing, f"dvc.yaml stage {stage} misses code deps {missing}"
    code = {d for d in deps if d.endswith(".py") or d in FOLDERS}
    extra = sorted(code - set(code_deps(stage)))
    assert not extra, f"dvc.yaml stage {stage} depends on code its flow never imports: {extra}"


@pytest.mark.parametrize("stage", sorted(DVC))
def test_params_cover_every_profile_of_each_block(stage):
    params = DVC[stage]["params"]
    blocks = [p for p in params if isinstance(p, str) and p != "profile"]
    assert "profile" in params and stage in blocks or stage not in {"simulate", "voxelize"}
    profile_keys = next(p["typ/profiles.yaml"] for p in params if isinstance(p, dict))
    assert sorted(profile_keys) == sorted(profile_params(blocks)), stage


def test_metric_code_reaches_evaluate_but_not_training():
    """Editing a generation metric re-runs evaluate alone (the issue's `dvc status` check)."""
    metric = "typ/metrics/generation.py"
    users = sorted(s for s in DVC if metric in DVC[s]["deps"])
    assert users == ["evaluate"], users
    assert metric in code_deps("evaluate")


def test_detection_scoring_code_reaches_evaluate_but_not_fusion_training():
    """Editing the AP metric or the fusion report re-runs evaluate alone: the fusion stage trains."""
    for code in ("typ/metrics/detection.py", "tasks/fusion_score.py", "tasks/fusion_report.py"):
        users = sorted(s for s in DVC if code in DVC[s]["deps"])
        assert users == ["evaluate"], (code, users)
    assert "artifacts/fusion/models" in DVC["evaluate"]["deps"]
    outs = {next(iter(o)) if isinstance(o, dict) else o for k in ("outs", "plots") for o in DVC["evaluate"].get(k, [])}
    assert {"reports/fusion.md", "reports/fusion_pr.png", "reports/fusion_robustness.png"} <= outs


def test_training_stages_read_no_held_out_split():
    """Adding a held-out scene retrains nothing: training stages depend on training data only."""
    for stage in ("vqvae", "stage1", "adapt", "stage2", "selftrain"):
        data = [d for d in DVC[stage]["deps"] if d.startswith("data/")]
        assert data, stage
        for d in data:  # a split folder, never a whole store
            split = d.rsplit("/", 1)[-1].removeprefix("split=")
            assert split in ("train", "val"), (stage, d)


@pytest.mark.parametrize("profile", ["tiny", "small", "paper"])
def test_scoring_stages_depend_on_the_splits_their_config_reads(profile):
    """generate, fusion and ddpm read a few split folders of the stores; depending on exactly those
    (not on the whole of data/sim) keeps a new held-out target scene from re-running fusion."""
    from tasks.fusion import Roots
    from typ.config import config_from_dict

    cfg = config_from_dict({"profile": profile})

    def data(stage):
        return {d for d in DVC[stage]["deps"] if d.startswith("data/")}

    roots = Roots.from_config(cfg.fusion, ROOT)
    assert data("fusion") == {str(p.relative_to(ROOT)) for p in vars(roots).values()}
    assert data("generate") == {f"{cfg.generate.input}/{s.dataset}/{s.split}" for s in cfg.generate.sets}
    d = cfg.ddpm
    assert data("ddpm") == {f"{d.input}/{d.domain}/{d.train_split}", f"{d.input}/{d.domain}/{d.test_split}",
                            f"{d.latent.voxels}/dataset={d.domain}/split={d.test_split}"}


def test_committed_code_deps_hash_the_sources_alone():
    """A code folder's hash in dvc.lock covers the files git tracks there and nothing else:
    the byte code Python writes beside them (``__pycache__``, whose bytes hold the source's
    mtime) must not make a fresh clone's ``dvc status`` differ from the machine that locked it."""
    import subprocess

    lock = yaml.safe_load((ROOT / "dvc.lock").read_text())
    checked = 0
    for name, stage in lock["stages"].items():
        for dep in stage.get("deps", []):
            path = ROOT / dep["path"]
            if not (path.is_dir() and dep["path"] in FOLDERS):
                continue
            tracked = subprocess.run(["git", "ls-files", "-z", dep["path"]], cwd=ROOT, capture_output=True,
                                     check=True).stdout.split(b"\0")
            files = [ROOT / f.decode() for f in tracked if f]
            assert dep["nfiles"] == len(files), (name, dep["path"])
            assert dep["size"] == sum(f.stat().st_size for f in files), (name, dep["path"])
            checked += 1
    assert checked > 0
    assert "__pycache__/" in (ROOT / ".dvcignore").read_text().split()
