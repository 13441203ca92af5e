"""Stage-1 sampling: time per sample against error, per sampler × steps × noise schedule.

    python bench/sampling.py [--out reports] [--views 8] [--steps 5,10,20,50,100,200]
        [--samplers ddim,dpmsolver++,unipc,ddpm] [--schedules linear,cosine,time_dependent]
        [--train-epochs N] [--quick]

Run from the repository root after `make run`. One process, one schedule after another:
- Models: the schedule of artifacts/stage1/seed_<stage1.seed>/ uses that model and its stored thresholds.
  A model trained with one β can't be sampled with another's, so every other schedule gets a
  stage-1 model trained here on the same encoded latents (tasks.stage1.train, the params.yaml
  stage1 block with only ``schedule`` and ``epochs`` replaced), its post-processing thresholds
  tuned on the first n val views with DDIM-200 (tasks.stage1.tune_thresholds), cached in
  artifacts/bench_sampling/<schedule>-<key>/ (key: config, VQ-VAE weights, train views, n).
- Every (sampler, steps) samples the same first n test views from the same x_T (generator
  seed stage1.seed + 2, as the stage does; with n = 8 the DDIM-200 row is the stage's own
  test sample), decodes them and post-processes them with the model's thresholds and noise seed.
  DDPM also runs the full chain (T = 1000 steps) outside --quick: it is the setting DDPM is made for.
- s/sample: median wall time of sample_logits (reverse process + VQ decoding) for the batch of n,
  divided by n; repeated up to 3 times while the repeats stay under 3 s. × DDIM-200: its time
  over this row's; × sampling: the same without the decoder's time (measured once, shared).
- Error against the truth (the simulated target views): JSD and MMD (r2dm preset, occupied voxel
  centres, typ.metrics), voxel IoU pooled over the n views. Against DDIM-200 from the same noise:
  |Δp| = mean |p - p_DDIM-200| of decoded occupancy probabilities, and IoU between the two volumes.
- Within 2 %: JSD <= 1.02 JSD(DDIM-200) and IoU >= 0.98 IoU(DDIM-200). Seed spread: the same
  numbers for DDIM-200 from other noise (seed + 3), i.e. how much of a difference n views can resolve.
- Schedules: linear (the pipeline's), cosine² and the LiDAR DDPM paper's time-dependent one by
  default; its ramp (Eq. 2-3) is within 0.008 of linear's ᾱ everywhere at T = 1000, so it would
  mostly repeat the linear rows (--schedules linear,ramp to check).
- Pareto: J / I mark rows no other row of the schedule beats on both time and JSD / IoU.
Writes <out>/bench_sampling.md, bench_sampling.png, bench_schedules.md and bench_sampling.csv (the
plot data dvc.yaml's ``sampling_pareto`` plot draws: one row per schedule × sampler × steps, seconds per
sample against 1 - IoU to the truth, with JSD and MMD) atomically; prints the tables.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

from typ.io import atomic_path, write_text  # noqa: E402

# torch, diffusers and the tasks are imported inside the functions that run models, so that the
# pure helpers (and their tests) load in milliseconds.
CACHE = Path("artifacts/bench_sampling")
REFERENCE = ("ddim", 200)
TOLERANCE = 0.02
FAST_STEPS = 20
#: sampler -> (colour, marker) in the plot; the order is the tables' order
SAMPLERS = {"ddim": ("tab:blue", "o"), "dpmsolver++": ("tab:orange", "s"), "unipc": ("tab:green", "^"),
            "ddpm": ("tab:red", "v")}


# ---------------------------------------------------------------- pure helpers


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the (cost, error) points that no other point beats on both, cheapest first.

    Both coordinates are minimised; NaN points are never on the front; of equal points the first wins.
    """
    order = sorted((i for i, (x, y) in enumerate(points) if not (math.isnan(x) or math.isnan(y))),
                   key=lambda i: points[i])
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def relative_gap(row: dict, ref: dict) -> float:
    """How much worse than ``ref`` the row is, relatively, on its worse of JSD (↓) and IoU (↑)."""
    return max(row["jsd"] / ref["jsd"] - 1.0, 1.0 - row["iou"] / ref["iou"])


def fastest_within(rows: list[dict], ref: dict, *, tol: float = TOLERANCE, max_steps: int = FAST_STEPS) -> dict | None:
    """The fastest row with <= max_steps steps whose JSD and IoU are within ``tol`` of ``ref``'s, or None."""
    ok = [r for r in rows if r["steps"] <= max_steps and relative_gap(r, ref) <= tol]  # NaN gap fails
    return min(ok, key=lambda r: r["seconds"]) if ok else None


def fmt(value: float, spec: str) -> str:
    return "–" if math.isnan(value) else format(value, spec)


def sampling_table(rows: list[dict], ref: dict, decode_s: float) -> str:
    """Markdown table of one schedule's rows (dicts as made by ``measure_schedule``)."""
    head = ("| sampler | steps | s/sample | × DDIM-200 | × sampling | JSD | MMD | IoU | mean abs Δp to DDIM-200 "
            "| IoU to DDIM-200 | Pareto |")
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    fronts = {key: {id(rows[i]) for i in pareto_front([(r["seconds"], f(r)) for r in rows])}
              for key, f in (("J", lambda r: r["jsd"]), ("I", lambda r: -r["iou"]))}
    for r in rows:
        latent = (ref["seconds"] - decode_s) / max(r["seconds"] - decode_s, 1e-9)
        mark = "".join(k for k, ids in fronts.items() if id(r) in ids)
        lines.append(f"| {r['sampler']} | {r['steps']} | {r['seconds']:.3f} | {ref['seconds'] / r['seconds']:.1f}× "
                     f"| {latent:.1f}× | {fmt(r['jsd'], '.4f')} | {fmt(r['mmd'], '.2e')} | {fmt(r['iou'], '.4f')} "
                     f"| {r['dp']:.4f} | {r['iou_ref']:.3f} | {mark} |")
    return "\n".join(lines)


def summary_line(schedule: str, rows: list[dict], ref: dict, spread: dict) -> str:
    """The verdict for one schedule: fastest <= 20-step row within 2 % of DDIM-200, or the closest one."""
    bound = (f"JSD <= {ref['jsd'] * (1 + TOLERANCE):.4f}, IoU >= {ref['iou'] * (1 - TOLERANCE):.4f}; "
             f"seed spread of DDIM-200: JSD {spread['jsd'] / ref['jsd'] - 1:+.1%}, IoU {spread['iou'] / ref['iou'] - 1:+.1%}")
    best = fastest_within(rows, ref)
    if best is not None:
        return (f"- **{schedule}**: {best['sampler']} at {best['steps']} steps is within {TOLERANCE:.0%} of DDIM-200 "
                f"({bound}) at {best['seconds']:.3f} s/sample, {ref['seconds'] / best['seconds']:.1f}× faster"
                f"{'' if ref['seconds'] / best['seconds'] >= 10 else ' (short of the 10× target)'}; "
                f"from the same noise it is {best['dp']:.4f} from DDIM-200 in mean abs Δp, IoU {best['iou_ref']:.3f}.")
    fast = [r for r in rows if r["steps"] <= FAST_STEPS and not math.isnan(relative_gap(r, ref))]
    if not fast:
        return f"- **{schedule}**: no configuration at <= {FAST_STEPS} steps was measured."
    near = min(fast, key=lambda r: relative_gap(r, ref))
    return (f"- **{schedule}**: none at <= {FAST_STEPS} steps is within {TOLERANCE:.0%} of DDIM-200 ({bound}); closest: "
            f"{near['sampler']} {near['steps']} steps, JSD {near['jsd'] / ref['jsd'] - 1:+.1%}, "
            f"IoU {near['iou'] / ref['iou'] - 1:+.1%}, {ref['seconds'] / near['seconds']:.1f}× faster.")


def schedules_table(results: dict, steps: list[int], recon: dict) -> str:
    """LiDAR-DDPM Table II analogue: DDIM at each step count, schedule × metric rows."""
    head = "| schedule | metric | " + " | ".join(f"{s} steps" for s in steps) + " |"
    lines = [head, "|" + "---|" * (len(steps) + 2)]
    for name, res in results.items():
        by_steps = {r["steps"]: r for r in res["rows"] if r["sampler"] == "ddim"}
        for metric, label, spec in (("jsd", "JSD ↓", ".4f"), ("mmd", "MMD ↓", ".2e"), ("iou", "IoU ↑", ".4f")):
            cells = [fmt(by_steps[s][metric], spec) if s in by_steps else "–" for s in steps]
            lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
    lines.append(f"| VQ-VAE reconstruction of the truth | JSD / MMD / IoU | {fmt(recon['jsd'], '.4f')} / "
                 f"{fmt(recon['mmd'], '.2e')} / {fmt(recon['iou'], '.4f')} |" + " |" * (len(steps) - 1))
    return "\n".join(lines)


def parse_list(text: str, kind=str) -> list:
    return [kind(v) for v in text.split(",") if v.strip()]


# ---------------------------------------------------------------- models and measurements


def schedule_model(block, schedule: str, epochs: int, vq: tuple, views: dict, n_val: int):
    """(model, thresholds, how) for ``schedule``: trained here, or loaded from the cache."""
    import torch

    from tasks import stage1 as stage
    from typ.config import as_dict
    from typ.io import hash_files, hash_obj

    cfg = dataclasses.replace(block, schedule=schedule, epochs=epochs)
    key = hash_obj({"cfg": as_dict(cfg), "n_val": n_val, "train": [list(k) for k in views["train"].keys],
                    "vqvae": hash_files([f for k in ("x", "y")
                                         for f in sorted((Path(block.vqvae) / k).glob("*.safetensors"))])})[:12]
    folder = CACHE / f"{schedule}-{key}"
    how = f"trained by this bench for {epochs} epoch(s), thresholds tuned on {n_val} val views ({folder})"
    if (folder / "config.json").exists():
        model, saved = stage.load_model(folder)
        return model, saved["postprocess"], how
    print(f"training a stage-1 model for schedule {schedule} ({epochs} epochs) in {folder}", file=sys.stderr)
    latents, cond = stage.encode_views(*vq, views["train"], dihedral=True)
    model = stage.train(cfg, latents, cond, seed=cfg.seed, views=len(views["train"]), out=folder,
                        log_fn=lambda values, step: None)
    val = subset(views["val"], n_val)
    val_true, _ = val.batch(range(len(val)))
    _, y_val = stage.encode_views(*vq, val)
    logits = stage.sample_logits(model, vq[0], y_val, cfg=cfg, generator=torch.Generator().manual_seed(cfg.seed + 1),
                                 sampler=REFERENCE[0], num_steps=REFERENCE[1])
    thresholds = stage.tune_thresholds(logits, val_true, cfg, cfg.seed)
    stage.save_model(model, cfg, thresholds, folder)
    return model, thresholds, how


def occupancy_metrics(occ, truth, grid) -> dict:
    """JSD / MMD (r2dm preset, occupied voxel centres) and pooled voxel IoU of (N, C, H, W) bool
    samples against the truth; ``empty_generated``: samples with no voxel (left out of JSD/MMD)."""
    from typ.metrics import jsd_bev, mmd_bev, occupancy_iou
    from typ.voxel import voxel_centers

    gen = [voxel_centers(o.transpose(1, 2, 0), grid) for o in occ]
    ref = [voxel_centers(t.transpose(1, 2, 0), grid) for t in truth]
    kept = [g for g in gen if len(g)]
    out = {"iou": occupancy_iou(occ, truth)["iou"], "empty_generated": len(gen) - len(kept)}
    if kept:
        out["jsd_r2dm"], out["mmd_r2dm"] = jsd_bev(ref, kept, "r2dm"), mmd_bev(ref, kept, "r2dm")
    return out


def subset(views, n: int):
    from tasks.voxel_data import ViewSet

    return ViewSet(views.grid, views.keys[:n], views.records[:n])


def timed(fn, *, repeats: int = 3, budget_s: float = 3.0):
    """(fn()'s result, median wall seconds): called up to ``repeats`` times while under ``budget_s``."""
    times, out = [], None
    while len(times) < repeats and sum(times) < budget_s:
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def measure_schedule(model, thresholds: dict, cfg, x_vq, y_lat, truth, grid, plan: list[tuple[str, int]]) -> dict:
    """Rows for every (sampler, steps) in ``plan`` against the truth and the DDIM-200 output."""
    import numpy as np
    import torch

    from models.postprocess import postprocess
    from tasks.stage1 import sample_logits
    from typ.metrics import occupancy_iou

    n = len(truth)

    def generate(sampler, steps, seed):
        return sample_logits(model, x_vq, y_lat, cfg=cfg, generator=torch.Generator().manual_seed(seed),
                             sampler=sampler, num_steps=steps)

    def score(logits, ref):
        occ = postprocess(logits, low=thresholds["low"], high=thresholds["high"], noise_std=thresholds["noise_std"],
                          generator=torch.Generator().manual_seed(cfg.seed)).numpy()
        m = occupancy_metrics(occ, truth, grid)
        p = torch.sigmoid(logits)
        row = {"jsd": m.get("jsd_r2dm", math.nan), "mmd": m.get("mmd_r2dm", math.nan), "iou": m["iou"],
               "empty": m["empty_generated"], "p": p, "occ": occ}
        row["dp"] = float((p - ref["p"]).abs().mean()) if ref else 0.0
        row["iou_ref"] = occupancy_iou(occ, ref["occ"])["iou"] if ref else 1.0
        return row

    logits, seconds = timed(lambda: generate(*REFERENCE, cfg.seed + 2))
    ref = {"sampler": REFERENCE[0], "steps": REFERENCE[1], "seconds": seconds / n, **score(logits, None)}
    spread = score(generate(*REFERENCE, cfg.seed + 3), ref)
    rows = [ref]
    for sampler, steps in plan:
        if (sampler, steps) == REFERENCE:
            continue
        logits, seconds = timed(lambda: generate(sampler, steps, cfg.seed + 2))
        rows.append({"sampler": sampler, "steps": steps, "seconds": seconds / n, **score(logits, ref)})
        r = rows[-1]
        print(f"  {sampler:>11} {steps:>4} steps  {r['seconds']:.3f} s/sample  JSD {r['jsd']:.4f}  IoU {r['iou']:.4f}"
              f"  |Δp| {r['dp']:.4f}", file=sys.stderr)
    for r in rows + [spread]:
        del r["p"], r["occ"]
    rows.sort(key=lambda r: (list(SAMPLERS).index(r["sampler"]), r["steps"]))
    return {"rows": rows, "ref": ref, "spread": spread, "empty": int(np.sum([r["empty"] for r in rows]))}


def plot_data(results: dict, path: Path) -> Path:
    """Every measured row as a table for ``dvc plots``: ``seconds`` (per sample) against ``error``
    (1 - voxel IoU to the truth), labelled ``setting`` (schedule sampler-steps), plus ``jsd``, ``mmd``."""
    from typ.plots import write_records

    rows = [{"seconds": r["seconds"], "error": 1.0 - r["iou"], "setting": f"{name} {r['sampler']}-{r['steps']}",
             "schedule": name, "sampler": r["sampler"], "steps": r["steps"], "jsd": r["jsd"], "mmd": r["mmd"],
             "iou": r["iou"]} for name, res in results.items() for r in res["rows"]]
    return write_records(path, rows)


def plot(results: dict, path: Path, title: str) -> None:
    from typ.reporting import subplots

    panels = (("jsd", "JSD to truth (r2dm, ↓)", False), ("iou", "voxel IoU to truth (↑)", False),
              ("dp", "mean |Δp| to DDIM-200, same noise (↓, log)", True))
    fig, axes = subplots(len(panels), len(results), figsize=(5.2 * len(results), 11), squeeze=False,
                             sharex="col")
    for col, (name, res) in enumerate(results.items()):
        ref = res["ref"]
        for row_i, (key, label, log_y) in enumerate(panels):
            ax = axes[row_i][col]
            rows = [r for r in res["rows"] if not (log_y and r[key] <= 0)]
            sign = -1.0 if key == "iou" else 1.0
            front = [rows[i] for i in pareto_front([(r["seconds"], sign * r[key]) for r in rows])]
            ax.step([r["seconds"] for r in front], [r[key] for r in front], where="post", color="0.6", ls="--",
                    lw=1, label="Pareto front", zorder=1)
            for sampler in SAMPLERS:
                pts = [r for r in rows if r["sampler"] == sampler]
                if not pts:
                    continue
                colour, marker = SAMPLERS[sampler]
                ax.plot([r["seconds"] for r in pts], [r[key] for r in pts], marker=marker, color=colour, label=sampler)
                for r in pts:
                    ax.annotate(str(r["steps"]), (r["seconds"], r[key]), fontsize=6, xytext=(3, 3),
                                textcoords="offset points")
            if key in ("jsd", "iou"):
                lo, hi = sorted((ref[key], ref[key] * (1 + sign * TOLERANCE)))
                ax.axhspan(lo, hi, color="tab:blue", alpha=0.12, label="within 2 % of DDIM-200")
                ax.axhline(res["spread"][key], color="k", lw=0.8, ls=":", label="DDIM-200, other noise")
                ax.plot([ref["seconds"]], [ref[key]], "k*", ms=12, label="DDIM-200 (reference)", zorder=5)
            ax.set_xscale("log")
            if log_y:
                ax.set_yscale("log")
            if row_i == len(panels) - 1:
                ax.set_xlabel("wall time per sample, s (sampling + decoding, log)")
            ax.set_ylabel(label)
            ax.grid(which="both", alpha=0.3)
            if row_i == 0:
                ax.set_title(f"schedule: {name}")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)


def parse_args(argv: list[str] | None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="reports", help="folder for bench_sampling.md/.png and bench_schedules.md")
    ap.add_argument("--views", type=int, default=8, help="test views sampled per configuration (one batch)")
    ap.add_argument("--steps", default="5,10,20,50,100,200", help="comma-separated sampler step counts")
    ap.add_argument("--samplers", default=",".join(SAMPLERS), help=f"comma-separated, of {list(SAMPLERS)}")
    ap.add_argument("--schedules", default="linear,cosine,time_dependent", help="comma-separated noise schedules")
    ap.add_argument("--train-epochs", type=int, default=None, help="epochs for the extra schedules' models "
                    "(default: stage1.epochs)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 2 views, steps 5,10, one extra schedule, 1 epoch")
    args = ap.parse_args(argv)
    if args.quick:
        args.views, args.steps, args.train_epochs = 2, "5,10", 1
        args.schedules = ",".join(parse_list(args.schedules)[:2])
    steps, samplers, schedules = parse_list(args.steps, int), parse_list(args.samplers), parse_list(args.schedules)

    from models.schedules import SCHEDULES

    bad = [s for s in samplers if s not in SAMPLERS] + [s for s in schedules if s not in SCHEDULES]
    if bad or not steps or min(steps) < 1 or args.views < 1:
        ap.error(f"unknown sampler/schedule {bad}" if bad else "--steps and --views need positive integers")
    return args, steps, samplers, schedules


def main(argv: list[str] | None = None) -> int:
    args, steps, samplers, schedules = parse_args(argv)

    import torch

    from tasks import stage1 as stage
    from tasks.voxel_data import load_views
    from tasks.vqvae import load_model as load_vqvae
    from typ.config import load_config

    cfg_all = load_config("params.yaml")
    block = cfg_all.stage1
    artifact = stage.replica_dir(Path(block.out), block.seed)
    if not (artifact / "config.json").exists():
        sys.exit(f"bench/sampling.py: {artifact} is missing: run `make run` first (from the repository root)")
    if max(steps) > block.train_timesteps:
        sys.exit(f"bench/sampling.py: --steps must be <= stage1.train_timesteps = {block.train_timesteps}")
    vq = tuple(load_vqvae(Path(block.vqvae) / k) for k in ("x", "y"))
    splits = {"train": block.train_split, "val": block.val_split, "eval": cfg_all.evaluate.target_split}
    views = {k: load_views(Path(block.input), dataset=block.dataset, split=split) for k, split in splits.items()}
    n = min(args.views, len(views["eval"]))
    test = subset(views["eval"], n)
    x_true, _ = test.batch(range(n))
    truth = x_true.numpy() > 0.5
    _, y_lat = stage.encode_views(*vq, test)
    base, saved = stage.load_model(artifact)
    with torch.no_grad():
        stage.sample_logits(base, vq[0], y_lat, cfg=block, generator=torch.Generator(), num_steps=1)  # warm-up
        latents = vq[0].encode_pre_quant(x_true)
        _, decode_s = timed(lambda: vq[0].decode_latents(latents))
        recon = occupancy_metrics((torch.sigmoid(vq[0](x_true).logits) > 0.5).numpy(), truth, test.grid)
    recon = {"jsd": recon.get("jsd_r2dm", math.nan), "mmd": recon.get("mmd_r2dm", math.nan), "iou": recon["iou"]}
    epochs = args.train_epochs or block.epochs

    results, notes = {}, []
    for schedule in schedules:
        if saved["schedule"] == schedule and saved["train_timesteps"] == block.train_timesteps:
            model, thresholds = base, saved["postprocess"]
            how = f"the pipeline's {artifact} and its thresholds"
        else:
            model, thresholds, how = schedule_model(block, schedule, epochs, vq, views, n)
        full_chain = [] if args.quick else [block.train_timesteps]
        plan = [(s, k) for s in samplers for k in sorted(set(steps + (full_chain if s == "ddpm" else [])))]
        print(f"schedule {schedule}: {how}", file=sys.stderr)
        cfg = dataclasses.replace(block, schedule=schedule)
        results[schedule] = measure_schedule(model, thresholds, cfg, vq[0], y_lat, truth, test.grid, plan)
        notes.append(f"- {schedule}: {how}; thresholds low {thresholds['low']}, high {thresholds['high']}.")

    tables = [f"### {name}\n\n{sampling_table(res['rows'], res['ref'], decode_s / n)}\n"
              for name, res in results.items()]
    verdicts = [summary_line(name, res["rows"], res["ref"], res["spread"]) for name, res in results.items()]
    machine = (f"{platform.processor() or platform.machine()}, torch {torch.__version__} with "
               f"{torch.get_num_threads()} threads, {n} test views in one batch")
    header = (f"Machine: {machine}. VQ decoding alone: {decode_s / n:.3f} s/sample. Empty generated views "
              f"(left out of JSD/MMD): {sum(r['empty'] for r in results.values())}.\n\nModels:\n" + "\n".join(notes))
    doc = __doc__.split("\n\n", 2)[2]
    text = "\n".join(tables) + "\n## Summary\n\n" + "\n".join(verdicts) + "\n"
    print(text)
    out = Path(args.out)
    write_text(out / "bench_sampling.md", f"# Stage-1 sampling: speed against error\n\n{doc}\n{header}\n\n{text}")
    ddim_steps = sorted(set(steps) | {REFERENCE[1]})
    table2 = schedules_table(results, ddim_steps, recon)
    print(table2)
    write_text(out / "bench_schedules.md", "# Noise schedules against DDIM steps (LiDAR DDPM Table II analogue)\n\n"
               f"DDIM (η = 0) on {n} test views, same noise per schedule; JSD/MMD r2dm preset, voxel IoU to the "
               f"truth. {machine}.\n\nModels:\n" + "\n".join(notes) + f"\n\n{table2}\n")
    plot_data(results, out / "bench_sampling.csv")
    plot(results, out / "bench_sampling.png",
         f"Stage-1 LDM sampling, {n} test views: time per sample vs error ({machine})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
