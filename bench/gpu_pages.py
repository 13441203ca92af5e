"""bench/gpu.py's pages: bench_gpu.md (the tables), README.md (how the run was made) and
bench_gpu.png (each figure against training time; bench/report.py links it as the page's plot),
from its results.json and, for the ratios, a ``--device cpu`` run's results.json. Partial
results give partial pages."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from tasks.evaluate import table
from typ.io import write_text
from typ.reporting import subplots
from typ.viz import save_png

#: (key, label) of the generation figures shown, as reports/generation_accuracy.md names them
FIGURES = [("iou", "IoU"), ("iou_above_ground", "IoU above ground"), ("object_hit_rate", "object hit rate"),
           ("jsd_r2dm", "JSD ↓"), ("iou_seen", "IoU seen"), ("iou_unseen", "IoU unseen"), ("chamfer_m", "Chamfer m ↓"),
           ("mmd_r2dm", "MMD ↓"), ("precision", "precision"), ("recall", "recall")]
#: the issue's targets: (what, figure, test)
TARGETS = ("x VQ-VAE reconstruction IoU ≥ 0.80", "TYP's above-ground IoU above the naive copy's",
           "object hit rate ≥ 0.85")
CURVES = [("recon_iou", "x VQ-VAE reconstruction IoU"), ("iou", "IoU"), ("iou_above_ground", "IoU above ground"),
          ("object_hit_rate", "object hit rate"), ("jsd_r2dm", "JSD (r2dm)")]


def num(v, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def interval(d: dict | None) -> str:
    """``value [low, high]`` of an intervals_json cell."""
    if not d or d.get("value") is None:
        return "–"
    if d.get("low") is None:
        return num(d["value"])
    return f"{d['value']:.3f} [{d['low']:.3f}, {d['high']:.3f}]"


def device_label(results: dict) -> str:
    """How the tables name the run's device: GPU, or (a --device cpu run) this run."""
    return "GPU" if results["run"].get("device_type") == "cuda" else "this run"


def ratio(a, b) -> str:
    return f"{a / b:.1f}×" if isinstance(a, (int, float)) and isinstance(b, (int, float)) and b else "–"


def rate(entry: dict | None, key: str = "steps_per_s") -> float | None:
    if not entry:
        return None
    return entry.get(key) if isinstance(entry.get(key), (int, float)) else None


def ratio_columns(g: str, cpu: dict | None) -> list[tuple[str, str]]:
    """The run's fp32 and bf16 columns, and with a CPU run to compare with, its and the ratios."""
    own = [("g32", f"{g} fp32"), ("g16", f"{g} bf16")]
    if cpu is None:
        return own
    return own + [("c32", "CPU fp32"), ("c16", "CPU bf16"), ("r32", f"{g}/CPU fp32"), ("r16", f"{g}/CPU bf16"),
                  ("r", f"{g} bf16 / CPU fp32")]


def timing_section(results: dict, cpu: dict | None) -> list[str]:
    t = results["phases"].get("timings")
    if not t:
        return []
    c = (cpu or {}).get("phases", {}).get("timings", {})
    cpu_name = (cpu or {}).get("run", {}).get("device")
    g = device_label(results)
    against = (f"; CPU: {cpu_name} ({cpu['run'].get('cores', '?')} cores, 1-minute load average "
               f"{cpu['run'].get('load_average_1min', '?')} at its start). Each device at its own batch (the GPU at "
               "the training batch; a CPU's samples/s hardly depends on it): the ratios are of samples/s (steps/s × "
               "batch). The last column is what a user gains moving from the CPU's best (fp32) to bf16 on the GPU"
               if cpu else "")
    lines = ["## Training samples/s", "",
             f"Each network's training step through its stage's training function; {g}: {results['run']['device']}"
             f"{against}. Generator networks at bench/gpu.yaml's size, the detectors and the pixel DDPM at the tiny "
             "profile's.", ""]
    rows = {}
    for name, e in t.get("networks", {}).items():
        cn = c.get("networks", {}).get(name, {})
        g32, g16, c32, c16 = (rate(e.get("fp32"), "samples_per_s"), rate(e.get("bf16"), "samples_per_s"),
                              rate(cn.get("fp32"), "samples_per_s"), rate(cn.get("bf16"), "samples_per_s"))
        rows[name] = {"gb": e.get("batch"), "cb": cn.get("batch", "–"), "g32": num(g32, 2), "g16": num(g16, 2),
                      "c32": num(c32, 4), "c16": num(c16, 4), "r32": ratio(g32, c32), "r16": ratio(g16, c16),
                      "r": ratio(g16, c32)}
    batches = [("gb", f"{g} batch")] + ([("cb", "CPU batch")] if cpu else [])
    lines += [table(rows, batches + ratio_columns(g, cpu), first="network"), ""]
    s, cs = t.get("sampling") or {}, c.get("sampling") or {}
    if s and "error" not in s and "skipped" not in s:
        lines += ["## Sampling views/s", "",
                  f"The whole generator at bench/gpu.yaml's size (x_e' encoded, adapter, reverse process, x decoded), "
                  f"a batch of {s.get('batch')} in this run" + (f" and {cs.get('batch')} on the CPU" if cs else "")
                  + (" (DDIM 200 extrapolated from 10 and 20 steps" + (" on the CPU)" if cs else ")")
                     if ((cs or s).get("fp32") or {}).get("ddim 200 extrapolated") else "") + ".", ""]
        rows = {}
        for sampler in ("dpmsolver++ 10", "ddim 200"):
            g32, g16 = (s.get("fp32") or {}).get(sampler), (s.get("bf16") or {}).get(sampler)
            c32, c16 = (cs.get("fp32") or {}).get(sampler), (cs.get("bf16") or {}).get(sampler)
            rows[sampler] = {"g32": num(g32), "g16": num(g16), "c32": num(c32, 4), "c16": num(c16, 4),
                             "r32": ratio(g32, c32), "r16": ratio(g16, c16), "r": ratio(g16, c32)}
        lines += [table(rows, ratio_columns(g, cpu), first="sampler"), ""]
    v, cv = t.get("voxelize") or {}, c.get("voxelize") or {}
    if v and "error" not in v and "skipped" not in v:
        lines += ["## Voxelization frames/s", "",
                  f"{v.get('points')}-point synthetic scans (bench/voxelize.py's). typ.voxel.voxelize runs on the "
                  "CPU (numba) on either machine; the same bins in torch run on the device ('voxels differing': "
                  "cells where its grids differ from typ's).", ""]
        rows = {}
        for grid, g in v.items():
            if not isinstance(g, dict):
                continue
            dev = next((k for k in g if k.startswith("torch")), None)
            cg = cv.get(grid, {}) if isinstance(cv.get(grid), dict) else {}
            rows[grid] = {"typ_g": num(g.get("typ (CPU, numba)"), 1), "torch_g": num(g.get(dev), 1),
                          "typ_c": num(cg.get("typ (CPU, numba)"), 1), "torch_c": num(cg.get("torch (cpu)"), 1),
                          "r": ratio(g.get(dev), cg.get("typ (CPU, numba)")), "diff": g.get("voxels differing")}
        lines += [table(rows, [("typ_g", "typ, GPU machine's CPU"), ("torch_g", "torch on the GPU"),
                               ("typ_c", "typ, this CPU"), ("torch_c", "torch, this CPU"),
                               ("r", "torch on GPU / typ here"), ("diff", "voxels differing")], first="grid"), ""]
    d = t.get("determinism") or {}
    if d and "error" not in d and "skipped" not in d:
        lines += ["## Run-to-run spread on CUDA", "",
                  "Two identical trainings (same seed, same batches), with typ's reproducibility flags "
                  "(typ.distributed.reproducible_cuda: no TF32, deterministic cuDNN and kernels) and without.", ""]
        rows = {}
        for flags, nets in d.items():
            for name, r in nets.items():
                rows[f"{name}, {flags}"] = {"eq": "yes" if r["bitwise_equal"] else "no", "max": f"{r['max_abs_diff']:.2e}",
                                            "rel": f"{r['relative_l2']:.2e}", "s": num(r["seconds_per_run"]),
                                            "ops": "; ".join(r["nondeterministic_ops"]) or "none"}
        lines += [table(rows, [("eq", "bitwise equal"), ("max", "max |Δw|"), ("rel", "relative L2"),
                               ("s", "s / run"), ("ops", "ops without a deterministic kernel")], first="run"), ""]
    return lines


def tests_section(results: dict) -> list[str]:
    t = results["phases"].get("tests")
    if not t or "tests" not in t:
        return [] if not t else ["## CUDA tests", "", f"tests/e2e/test_cuda.py did not report: {t.get('status')}", ""]
    lines = ["## CUDA tests", "",
             f"tests/e2e/test_cuda.py: {t['passed']} passed, {t['failures']} failed, {t['errors']} errors, "
             f"{t['skipped']} skipped of {t['tests']} ({t.get('seconds', '?')} s).", ""]
    bad = [c for c in t["cases"] if c["outcome"] in ("failure", "error")]
    if bad:
        lines += [table({c["name"]: {"o": c["outcome"], "m": c["message"][:200].replace("\n", " ")} for c in bad},
                        [("o", "outcome"), ("m", "message")], first="test"), ""]
    return lines


def generation_section(results: dict) -> list[str]:
    tr = results["phases"].get("train")
    if not tr or "final" not in tr:
        return []
    final, base, tiny = tr["final"], tr.get("baselines", {}), (tr.get("tiny") or {})
    tiny_gen = (tiny.get("evaluate") or {}).get("generation", {})
    n = tr.get("data", {}).get("pairs", "?")
    lines = ["## The generator at GPU size", "",
             f"{n} held-out (ego, reference) pairs of target/test, scored as the evaluate stage scores generation "
             "(figures pooled over the pairs, 95 % bootstrap interval over scenes). GPU columns: bench/gpu.yaml's "
             f"grid ({'×'.join(str(s) for s in tr['config']['voxelize']['grid']['shape'])}); tiny columns: "
             "the tiny profile's grid (128×128×8) on the same scenes"
             + ("" if tiny.get("same_scenarios") else " (not checked byte-identical: the tiny project was not given "
                                                       "or differs)") + ".", ""]
    columns = [("naive_copy", "naive copy, GPU grid", base.get("naive_copy")),
               ("resim", "re-simulation, GPU grid", base.get("resim")),
               ("tiny_copy", "tiny: naive copy", tiny_gen.get("naive_copy")),
               ("tiny_typ", "tiny: TYP", tiny_gen.get("disc_st_dummy")),
               ("stage1_only", "GPU size: stage 1 only", final.get("stage1_only")),
               ("disc", "GPU size: stage 2", final.get("disc")), ("typ", "GPU size: TYP", final.get("typ"))]
    rows = {"x VQ-VAE reconstruction IoU": {
        "tiny_typ": num(((tiny.get("vqvae_x") or {}).get("iou"))), "typ": num((final.get("vqvae_x") or {}).get("iou"))}}
    for key, label in FIGURES:
        rows[label] = {c: interval((d or {}).get(key)) for c, _, d in columns}
    lines += [table(rows, [(c, h) for c, h, _ in columns], first="figure"), "",
              "The x VQ-VAE row: its reconstruction of the pairs' true views (threshold 0.5), tiny's x VQ-VAE in the "
              "tiny column, the GPU run's in the TYP column.", ""]
    lines += verdicts(final, base)
    return lines


def verdicts(final: dict, base: dict) -> list[str]:
    """The issue's three targets, each met or not (``- **`` lines: bench.md keeps them)."""
    typ = final.get("typ") or final.get("disc") or {}
    which = "TYP" if "typ" in final else "stage 2 (self-training did not finish)"
    recon = (final.get("vqvae_x") or {}).get("iou")
    above, copy_above = (typ.get("iou_above_ground") or {}), (base.get("naive_copy") or {}).get("iou_above_ground", {})
    hits = (typ.get("object_hit_rate") or {}).get("value")
    out = []
    if recon is not None:
        out.append(f"- **x VQ-VAE reconstruction IoU {recon:.3f}: target ≥ 0.80 {'met' if recon >= 0.8 else 'not met'}**")
    if above.get("value") is not None and copy_above.get("value") is not None:
        beats = above["low"] is not None and copy_above.get("high") is not None and above["low"] > copy_above["high"]
        word = "above (intervals apart)" if beats else "above" if above["value"] > copy_above["value"] else "not above"
        out.append(f"- **{which} above-ground IoU {interval(above)} against the naive copy's {interval(copy_above)}: "
                   f"{word}**")
    if hits is not None:
        out.append(f"- **{which} object hit rate {hits:.3f}: target ≥ 0.85 {'met' if hits >= 0.85 else 'not met'}**")
    return out + ([""] if out else [])


def training_section(results: dict) -> list[str]:
    tr = results["phases"].get("train")
    if not tr or not tr.get("networks"):
        return []
    lines = ["## Training at GPU size", "",
             f"Precision {tr.get('precision')}; {num(tr.get('train_s'), 0)} s of training in all (probes excluded)."
             + (f" {tr['cut'].capitalize()}." if tr.get("cut") else ""), ""]
    rows = {name: {"e": r.get("epochs"), "s": f"{r.get('steps_run', '–')} / {r.get('steps_planned')}",
                   "t": num(r.get("seconds"), 1), "r": num(r.get("steps_per_s"), 2), "l": num(r.get("last_loss"), 4),
                   "st": r.get("status")} for name, r in tr["networks"].items()}
    lines += [table(rows, [("e", "epochs"), ("s", "steps run / planned"), ("t", "seconds"), ("r", "steps/s"),
                           ("l", "last loss"), ("st", "status")], first="network"), ""]
    curve = tr.get("curve", [])
    if curve:
        keys = [k for k, _ in CURVES if any(k in p for p in curve)]
        rows = {f"{p['network']} step {p['step']}": {"t": num(p["train_s"], 1), **{k: num(p.get(k)) for k in keys}}
                for p in curve}
        lines += ["### Each figure against training time (bench_gpu.png)", "",
                  "At each checkpoint, scored on the same pairs (generation probes: post-processing threshold 0.5 for "
                  "stage 1, its tuned thresholds after; 100 bootstrap replicates).", "",
                  table(rows, [("t", "training s"), *((k, dict(CURVES)[k]) for k in keys)], first="checkpoint"), ""]
    return lines


def bench_page(results: dict, cpu: dict | None) -> str:
    run = results["run"]
    lines = ["# typ's GPU bench, its CPU side" if run.get("device_type") == "cpu" else
             "# typ on a GPU: throughput beside the CPU, and the generator at GPU size", "",
             f"`{run['command']}` at {run.get('commit') or '?'}{' (uncommitted changes)' if run.get('dirty') else ''}, "
             f"{run['device']}, torch {run['torch']}, {run['started']}, {run.get('wall_s')} s. "
             "How it was made and what it could not do: README.md beside this page.", ""]
    lines += tests_section(results) + timing_section(results, cpu) + generation_section(results) \
        + training_section(results)
    return "\n".join(lines) + "\n"


def readme(results: dict) -> str:
    run = results["run"]
    phases = results["phases"]
    cpu_side = run.get("device_type") == "cpu"
    lines = ["# typ's GPU bench, its CPU side: how this folder was made" if cpu_side else
             "# typ on a GPU: how this folder was made", "",
             "Made by one run of `bench/gpu.py` (its docstring says what each phase does) on the data "
             "`bench/gpu_data.py` made on the CPU; the tables are in bench_gpu.md, every number in results.json."
             + (" A `--device cpu` run: the CPU side of the GPU run's ratios (reports/gpu/bench_gpu.md reads its "
                "results.json), each network at a small batch." if cpu_side else ""), "",
             f"- command: `{run['command']}`",
             f"- commit: {run.get('commit') or 'unknown (no git there: pass --commit)'}"
             f"{' with uncommitted changes' if run.get('dirty') else ''}",
             f"- device: {run['device']} ({run.get('cores')} CPU cores, torch on {run.get('torch_threads')} threads, "
             f"1-minute load average {run.get('load_average_1min')} at the start), torch {run['torch']}, "
             f"CUDA {run.get('cuda')}, Python {run['python']}, numpy {run['numpy']}",
             f"- started {run['started']}; wall time {run.get('wall_s')} s of a {run['minutes']}-minute deadline", "",
             "## Phases", ""]
    rows = {name: {"s": p.get("status"), "t": p.get("seconds", "–"),
                   "n": p.get("error") or p.get("reason") or p.get("cut") or ""} for name, p in phases.items()}
    lines += [table(rows, [("s", "status"), ("t", "seconds"), ("n", "note")], first="phase"), ""]
    missing = []
    t = phases.get("timings", {})
    for name, entry in (t.get("networks") or {}).items():
        for precision in ("fp32", "bf16"):
            e = entry.get(precision, {})
            if "error" in e or "skipped" in e:
                missing.append(f"- timing of {name} in {precision}: {e.get('error') or e.get('skipped')}")
    for part in ("sampling", "voxelize", "determinism"):
        if isinstance(t.get(part), dict) and ("error" in t[part] or "skipped" in t[part]):
            missing.append(f"- {part}: {t[part].get('error') or t[part]['skipped']}")
    tr = phases.get("train", {})
    for name, r in (tr.get("networks") or {}).items():
        if r.get("status") != "done":
            missing.append(f"- training of {name}: {r.get('status')}")
    if tr.get("cut"):
        missing.append(f"- {tr['cut']}")
    missing += [f"- final score of {name}: {v['error']}" for name, v in (tr.get("final") or {}).items()
                if isinstance(v, dict) and "error" in v]
    missing += [f"- probe of {p['network']} at step {p['step']}: {p['error']}" for p in tr.get("curve") or []
                if "error" in p]
    lines += [f"## What could not be done in the {'run' if cpu_side else 'lease'}", "",
              *(missing or ["- (nothing recorded)"]), ""]
    return "\n".join(lines) + "\n"


def curves_figure(results: dict) -> Figure | None:
    curve = (results["phases"].get("train") or {}).get("curve") or []
    if not curve:
        return None
    fig, axes = subplots(1, len(CURVES), figsize=(3.2 * len(CURVES), 3.0), dpi=100, layout="constrained")
    networks = list(dict.fromkeys(p["network"] for p in curve))
    for ax, (key, label) in zip(axes, CURVES):
        for net in networks:
            pts = [(p["train_s"], p[key]) for p in curve if p["network"] == net and p.get(key) is not None]
            if pts:
                ax.plot(*zip(*pts), marker="o", ms=3, label=net)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("training seconds", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=7)
    return fig


def write(out: Path, results: dict, cpu: dict | None) -> None:
    write_text(out / "bench_gpu.md", bench_page(results, cpu))
    write_text(out / "README.md", readme(results))
    fig = curves_figure(results)
    if fig is not None:
        save_png(fig, out / "bench_gpu.png")
