"""bench/pipeline.py's pure parts and bench/report.py's aggregation, without running dvc.

The report writer on synthetic timings, the process-tree monitor on a tiny child process,
the fusion timing at one repetition on a tiny detector, and reports/bench.md's digest.
"""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench_modules import ROOT, load_bench


bench = load_bench("pipeline")
report = load_bench("report")

MACHINE = {"cores": 2, "cpu": "Test CPU", "torch": "2.13.0", "torch_threads": 1, "python": "3.11.7"}
STAMP = {"when": "2025-01-01 00:00 UTC", "machine": MACHINE}


def _stage(seconds, rss=500.0, hwm=400.0, cpu=None):
    return {"seconds": seconds, "peak_rss_mb": rss, "peak_process_mb": hwm, "cpu_s": seconds if cpu is None else cpu}


def _pipeline(inc_seconds: float, scale: int = 2) -> dict:
    gen = {"scenarios": 3, "frames": 6, "references": 6, "reference_too_close": 1, "reference_out_of_range": 5,
           "scenario_without_candidate_vehicle": 0, "skipped_unchanged": 0, "seconds_generating": 3.0,
           "seconds_per_reference": 0.5}
    return {**STAMP, "scale": scale, "params": bench.small_params(scale), "added": ["target", "test"],
            "stages": ["simulate", "voxelize", "generate"],
            "full": {"seconds": 100.0, "ran": ["simulate", "voxelize", "generate"], "noop": False,
                     "stages": {"simulate": _stage(30.0), "voxelize": _stage(20.0), "generate": _stage(40.0)},
                     "scenario_counts": {}, "generate": gen, "work": {"simulate": 2.0, "voxelize": None,
                                                                      "generate": 3.0}},
            "noop": {"seconds": 4.0, "ran": [], "noop": True, "stages": {}, "scenario_counts": {}, "generate": gen},
            "incremental": {"seconds": inc_seconds, "ran": ["simulate", "generate"], "noop": False,
                            "stages": {"simulate": _stage(inc_seconds / 2), "generate": _stage(inc_seconds / 4)},
                            "scenario_counts": {"simulate": {"redone": 1, "scenarios": 7}},
                            "generate": {**gen, "scenarios": 4, "references": 8, "skipped_unchanged": 3,
                                         "seconds_generating": 1.0}}}


def _paper() -> dict:
    rows = [{"name": "VQ-VAE x", "what": "train", "params_m": 10.0, "seconds": 2.0, "epochs": 120, "n": 10},
            {"name": "stage-2 adapter", "what": "train", "params_m": 1.0, "seconds": 1.0, "epochs": 2, "n": 10,
             "assumed": True}]
    rows += [{"name": n, "what": "", "params_m": None, "seconds": 0.5} for n in bench.GENERATION_PARTS]
    rows.append({"name": "denoising step", "what": "", "params_m": 8.0, "seconds": 0.1})
    return {**STAMP, "steps": 2, "sample_steps": 200, "n_gen": 100, "pseudo_references": 10, "rows": rows}


def test_small_params_scale_every_split_and_load():
    from typ.config import config_from_dict

    params = bench.small_params(3)
    assert params["simulate"]["scenarios"]["target"] == {"train": 3, "val": 3, "test": 3, "pretrain": 3}
    assert params["simulate"]["scenarios"]["real_cav"]["test"] == 3
    assert bench.SMALL["simulate"]["scenarios"]["target"]["train"] == 1          # not modified in place
    assert bench.with_added_scenario(params)["simulate"]["scenarios"]["target"]["test"] == 4
    cfg = config_from_dict(params)
    assert cfg.simulate.scenarios["source"]["test"] == 3 and cfg.fusion.steps == 2


def test_pipeline_stages_follow_config_order_and_dvc_yaml():
    assert bench.pipeline_stages({"stages": {"generate": {}, "simulate": {}, "other": {}}}) == ["simulate", "generate"]


def test_stage_table_and_incremental_verdict():
    met = _pipeline(inc_seconds=50.0)                          # 0.50 <= 1.5 / 2
    lines = bench.stage_table(met).splitlines()
    assert all(line.count("|") == lines[0].count("|") for line in lines)
    assert "work reported s (full)" in lines[0]
    assert lines[2] == "| simulate | 30.0 | 30% | 30.0 | 2.0 | 500 | 400 | 25.0 | 25.0 | 0.83 | 0.83 |"
    assert lines[3].endswith("| – | 500 | 400 | skipped | | 0 | 0 |")    # voxelize: no work reported, not rerun
    assert lines[5].startswith("| dvc (start, hashing, checks) | 10.0 | 10% |")   # 100 - 90
    assert lines[6].endswith("| 5.0 | 500 | 400 | **50.0** | 37.5 | **0.50** | 0.42 |")
    verdicts = bench.incremental_verdicts(met)
    assert "0.50 × the full run" in verdicts[0] and "CPU time 0.42 ×" in verdicts[0]   # 37.5 / 90
    assert "target ≤ 1.5/N = 0.75: met." in verdicts[0] and "Stages rerun: 2 of 3" in verdicts[0]
    assert "simulate 1 of 7" in verdicts[0] and "ran no stage" in verdicts[1]
    # simulate and generate report 2 + 3 s of work; beyond it they spend 28 and 37 CPU s
    assert "report 5.0 s of it in 70.0 s wall; the median stage spends 32.5 CPU s beyond" in verdicts[2]
    assert "**not met**" in bench.incremental_verdicts(_pipeline(inc_seconds=80.0))[0]
    assert "vacuous" in bench.incremental_verdicts(_pipeline(inc_seconds=80.0, scale=1))[0]


def test_skip_rows_by_hand():
    rows = bench.skip_rows("d", {"scenarios": 4, "frames": 8, "references": 8, "reference_too_close": 2,
                                 "reference_out_of_range": 6, "scenario_without_candidate_vehicle": 1,
                                 "skipped_unchanged": 2, "seconds_generating": 2.0, "seconds_per_reference": 0.5},
                           references_per_frame=2)
    band, none, unchanged = rows
    assert (band["skipped"], band["of"], band["views"], band["saved_s"]) == (8, 16, 8, 4.0)
    assert (none["skipped"], none["of"], none["views"], none["saved_s"]) == (1, 4, 4.0, 2.0)   # 2 frames x 2 refs
    assert (unchanged["views"], unchanged["saved_s"]) == (4, 2.0)       # 8 references, 4 generated in 2 s
    table = bench.skip_table(rows).splitlines()
    assert table[2] == "| d | reference views outside the distance band | 8 of 16 | 50.0% | 8 | 0.500 | 4.0 s |"
    nothing = bench.skip_rows("n", {"scenarios": 2, "references": 0, "reference_out_of_range": 3}, 1)
    assert nothing[0]["saved_s"] is None and "nothing generated" in bench.skip_table(nothing)


def test_paper_extrapolation_formula():
    rows = {r["name"]: r for r in bench.extrapolate(_paper())}
    assert rows["VQ-VAE x"]["total"] == pytest.approx(2.0 * 120 * 10)
    assert rows["stage-2 adapter"]["formula"] == "2 epochs × 10 (assumed)"
    per_gen = 4 * 0.5 + 200 * 0.1
    assert rows["generation (ColWaymo)"]["per_sample"] == pytest.approx(per_gen)
    assert rows["generation (ColWaymo)"]["total"] == pytest.approx(100 * per_gen)
    assert rows["self-training pseudo references"]["total"] == pytest.approx(10 * per_gen)
    assert bench.duration(90) == "90.0 s" and bench.duration(7200) == "2.0 h" and bench.duration(3 * 86400) == "3.0 d"


def test_report_files_from_synthetic_sections(tmp_path):
    methods = {"none": {"frame_s": 0.01, "network_s": 0.005}, "late": {"frame_s": 0.03, "network_s": 0.015}}
    fusion = {**STAMP, "load": 3.5, "agents": 3, "points": 100, "repeats": 1,
              "profiles": {"tiny": {"detector": "d", "methods": methods}}}
    skipping = {**STAMP, "source": "metrics/generate.json", "references_per_frame": 2,
                "default": {"scenarios": 2, "frames": 4, "references": 4, "reference_out_of_range": 4,
                            "seconds_generating": 2.0, "seconds_per_reference": 0.5}}
    store = {"pipeline": _pipeline(50.0), "skipping": skipping, "paper": _paper(), "fusion": fusion}
    bench.write_report(store, tmp_path)
    text = (tmp_path / "bench_pipeline.md").read_text()
    assert "| tiny | d | late | 30.0 | 3.00× | 15.0 | 3.00× |" in text
    assert "| default data | reference views outside the distance band | 4 of 8 | 50.0% |" in text
    assert "| bench N = 2, +1 scenario | scenarios unchanged since the last run | 3 of 4 |" in text
    assert "Measured 2025-01-01 00:00 UTC on 2 cores (Test CPU)" in text
    assert "with 1 intra-op thread(s); 1-minute load average 3.5 at the start." in text
    assert json.loads((tmp_path / "bench_pipeline.json").read_text())["fusion"]["agents"] == 3
    assert (tmp_path / "bench_pipeline.png").stat().st_size > 1000
    digest = report.digest(text)
    assert sum(line.startswith("|---") for line in digest.splitlines()) == 5        # one per table
    assert "- **incremental**" in digest and "### Skipping" in digest
    assert "Run from the repository root" not in digest              # the method text stays on the page


def test_aggregate_keeps_titles_tables_and_verdicts(tmp_path):
    (tmp_path / "bench_a.md").write_text("# A bench\n\nmethod text\n\n| x | y |\n|---|---|\n| 1 | 2 |\n\n"
                                         "## Summary\n\n- **fast**: yes\n- plain bullet\n")
    (tmp_path / "bench_b.md").write_text("# B bench\n\n## nothing tabular\n\ntext only\n")
    (tmp_path / "bench_a.png").write_bytes(b"png")
    text = report.aggregate(tmp_path, MACHINE)
    assert text.startswith("# typ benchmarks\n\nMachine: 2 cores (Test CPU), Python 3.11.7, torch 2.13.0 with 1")
    a, b = text.index("## A bench"), text.index("## B bench")
    assert a < b and "[plot](bench_a.png)" in text[a:b] and "[plot]" not in text[b:]
    assert "| 1 | 2 |" in text and "### Summary\n\n- **fast**: yes" in text
    assert "method text" not in text and "plain bullet" not in text and "nothing tabular" not in text
    assert "(no tables)" in text[b:]


def test_monitor_charges_a_child_tree_to_its_stage():
    child = ("import subprocess, sys, time; x = bytearray(60 * 2**20); "
             "subprocess.run([sys.executable, '-c', 'import time; y = bytearray(30 * 2**20); time.sleep(0.5)']); "
             "time.sleep(0.2)")
    cmd = [sys.executable, "-c", f"import subprocess, sys; subprocess.run([sys.executable, '-c', {child!r}, "
           "'typ', 'run', 'voxelize'], check=True)"]
    result = bench.measured(cmd, ROOT, dict(os.environ))
    assert result["ran"] == ["voxelize"] and result["noop"]
    stage = result["stages"]["voxelize"]
    assert 0.6 <= stage["seconds"] <= result["seconds"] + bench.POLL_S
    assert stage["peak_process_mb"] >= 60 and stage["peak_rss_mb"] >= 90   # both processes at once
    with pytest.raises(RuntimeError, match="failed"):
        bench.measured([sys.executable, "-c", "raise SystemExit(3)"], ROOT, dict(os.environ))


@pytest.mark.usefixtures("one_torch_thread")
def test_fusion_timing_on_a_tiny_detector():
    from typ.config import config_from_dict

    cfg = config_from_dict({"profile": "tiny"}).fusion
    small = dataclasses.replace(cfg.detector, lidar_range=(-12.8, -6.4, -3.0, 12.8, 6.4, 1.0), voxel_size=0.4,
                                max_pillars=2000)
    v2x = dataclasses.replace(cfg.v2xvit, dim=16, heads=2, dim_head=8, window_sizes=(2, 4), window_heads=(2, 2),
                              window_dim_heads=(8, 8), mlp_dim=16)
    times = bench.time_fusion(dataclasses.replace(cfg, detector=small, v2xvit=v2x), agents=2, points=500, repeats=1)
    assert set(times) == set(cfg.methods)
    assert all(0 < t["network_s"] and 0 < t["frame_s"] for t in times.values())


def test_cli_rejects_unknown_sections():
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "pipeline.py"), "--only", "pipeline,speed"],
                          capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 2 and "--only: expected sections of" in proc.stderr


def test_bench_pages_go_to_mlflow_as_one_run(tmp_path, monkeypatch):
    from mlflow.tracking import MlflowClient

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlruns.db'}")
    (tmp_path / "params.yaml").write_text("profile: tiny\n")
    pages = tmp_path / "reports"
    pages.mkdir()
    for name in ("bench.md", "bench_a.md", "bench_a.png", "bench_a.json", "fusion.md", "bench_notes.txt"):
        (pages / name).write_text(name)
    run_id = report.log_to_mlflow(pages, root=tmp_path)
    client = MlflowClient()
    run = client.get_run(run_id)
    assert run.info.run_name == "bench" and run.data.tags["mlflow.source.git.commit"]
    assert run.data.metrics["bench_pages"] == 1
    logged = sorted(Path(a.path).name for a in client.list_artifacts(run_id, "bench"))
    assert logged == ["bench.md", "bench_a.json", "bench_a.md", "bench_a.png"]   # bench pages only


def _overhead(noop_wall: float = 3.0) -> dict:
    full = {"seconds": 410.0, "ran": ["simulate", "vqvae"], "noop": False,
            "stages": {"simulate": _stage(100.0, cpu=90.0), "vqvae": _stage(300.0, cpu=280.0)},
            "flow_s": {"simulate": 97.0, "vqvae": 292.0}, "mlflow_start_s": {"simulate": 1.0, "vqvae": 2.0}}
    noop = {"wall_s": [noop_wall + 1.0, noop_wall, noop_wall + 0.5], "cpu_s": [2.0, 2.5, 3.0]}
    return {**STAMP, "repeats": 3, "params": "profile: tiny\n", "server_s": 6.0, "full": full,
            "startup": {"typ --help": [0.2, 0.3, 0.25], "typ check": [0.4, 0.5, 0.3]},
            "noop": {"simulate, shared server": noop, "voxelize, shared server": noop,
                     "voxelize, temporary server": {"wall_s": [12.0], "cpu_s": [14.0]}},
            "baseline": {"rev": "main", "sha": "abc1234", "startup": {"typ --help": [0.3], "typ check": [0.4]},
                         "noop": {"voxelize, temporary server": {"wall_s": [15.0, 16.0, 14.0], "cpu_s": [15.7]}}}}


def test_overhead_fixed_cost_by_hand():
    result = _overhead()
    totals = bench.overhead_totals(result)
    # fixed: simulate 100 - 97 + 1 = 4, vqvae 300 - 292 + 2 = 10, server 6; pipeline wall: 410 + 6
    assert totals["fixed"] == pytest.approx(20.0) and totals["wall"] == pytest.approx(416.0)
    assert totals["ratio"] == pytest.approx(20.0 / 416.0) and totals["unmeasured"] == []
    table = bench.overhead_table(result).splitlines()
    assert all(line.count("|") == table[0].count("|") for line in table)
    assert table[2] == "| simulate | 100.0 | 97.0 | 1.00 | 4.0 | 1.0% | 90.0 |"
    assert table[4] == "| Prefect server start (once) | 6.0 | – | – | 6.0 | 1.4% | – |"
    assert table[5] == "| dvc (start, hashing, checks) | 10.0 | | | | | |"
    assert table[6] == "| **pipeline** | **416.0** | | | **20.0** | **4.8%** | 370.0 |"
    noop = bench.noop_table(result).splitlines()
    assert noop[2] == "| this branch | simulate, shared server | 3.50 | 3.00 – 4.00 | 2.50 | 0.88 |"
    assert noop[-1] == "| main (abc1234) | voxelize, temporary server | 15.00 | 14.00 – 16.00 | 15.70 | 3.75 |"
    verdicts = bench.overhead_verdicts(result)
    assert "took 3.50 s wall (median of 3) = 0.88 × the 4 s target: met. main's code took 15.00 s" in verdicts[0]
    assert "(4.3 × as long)" in verdicts[0]
    assert "20.0 s of the tiny pipeline's 416.0 s wall = 4.8%; target ≤ 10%: met." in verdicts[1]
    assert "`typ --help` 0.25 s, `typ check` 0.40 s; target < 1 s: met." in verdicts[2]
    assert "**not met**" in bench.overhead_verdicts(_overhead(noop_wall=4.5))[0]
    missing = _overhead()
    del missing["full"]["flow_s"]["vqvae"]       # a stage without a flow run is named, not counted
    assert bench.overhead_totals(missing)["unmeasured"] == ["vqvae"]
    assert "(not measured: vqvae)" in bench.overhead_verdicts(missing)[1]


def test_overhead_section_renders_and_the_baseline_runs_through_its_own_entry_point(tmp_path):
    bench.write_report({"overhead": _overhead()}, tmp_path)
    text = (tmp_path / "bench_pipeline.md").read_text()
    assert "## Fixed cost per stage: the tiny pipeline, stages with nothing to do, the CLI" in text
    assert "| main (abc1234) | `typ --help` | 0.30 | 0.30 |" in text
    (tmp_path / "pyproject.toml").write_text('[project]\nname = "x"\n[project.scripts]\ntyp = "typ.cli:main"\n')
    cmd = bench.typ_command(tmp_path)
    assert cmd[1] == "-c" and "from typ.cli import main; sys.exit(main())" in cmd[2]


def test_mlflow_start_comes_from_the_stage_runs_tags(tmp_path, monkeypatch):
    from mlflow.tracking import MlflowClient

    from typ.config import config_from_dict
    from typ.tracking import stage_run

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlruns.db'}")
    with stage_run("simulate", config_from_dict({"profile": "tiny"}), root=tmp_path) as run:
        pass
    tag = float(MlflowClient(f"sqlite:///{tmp_path / 'mlruns.db'}").get_run(run.run_id).data.tags["typ.mlflow_start_s"])
    assert 0 < tag < 60
    import time
    assert bench.mlflow_starts(tmp_path, since=time.time() - 600) == {"simulate": tag}
    assert bench.mlflow_starts(tmp_path, since=time.time() + 600) == {}
