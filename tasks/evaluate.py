"""Stage ``evaluate``: every table the benchmark reports, on held-out data only, with intervals.

The training stages keep what training needs (losses, validation figures, thresholds); this
stage scores the trained models on held-out scenes and writes the reports, the plot data and
the gallery:

- generation accuracy (:mod:`tasks.evaluate_generation`): every method and baseline, per
  range band, seen / unseen cells, above the ground, object hit rate, Chamfer, JSD / MMD
  (r2dm preset), TYP Table 4 (adaptation ablation) and Table 5 (one- vs two-stage) analogues,
  the adaptation's source -> target distance, the sample-to-sample spread;
- ``reports/gallery/``: ego, x_e', generated, true and re-simulated views side by side;
- the collaborative detection benchmark (:func:`tasks.fusion.score_trained` of the networks the
  fusion stage saved): AP@0.5 / 0.7 by range on real_cav's test split for TYP Tables 1–3 and
  the robustness sweeps, ``reports/fusion.md`` and its plots.

Figures are pooled over pairs and given as ``value [low, high]``, a 95 % bootstrap interval
over scenes and training seeds (:mod:`typ.metrics.intervals`); a report says one method
"beats" another only where the intervals do not overlap.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from tasks import evaluate_generation as gen
from tasks import genscore, realism, selftrain
from tasks.scene_stage import StageResult
from typ.io import write_text
from typ.metrics.intervals import Interval, interval_cell
from typ.registry import METHODS, PLOTTED_GENERATION_METHODS, Plot, declare
from typ.reporting import markdown_table

LOG = logging.getLogger(__name__)

GENERATION_REPORT = Path("reports") / "generation_accuracy.md"
#: the methods whose curves dvc.yaml's plots declare (a method that did not run is an empty column)
PLOTTED = PLOTTED_GENERATION_METHODS
GALLERY = Path("reports") / "gallery"

ACCURACY_COLUMNS = [(name, m.label) for name, m in genscore.METRICS.items() if m.in_table]
#: the adaptation ablation's rows (TYP Table 4), as tasks.selftrain names them
TABLE4 = tuple(v.name for v in selftrain.TABLE4)


def _sweep(name: str, x: str, x_label: str, title: str) -> Plot:
    return Plot(f"fusion_{name}", x, {f"reports/plots/fusion_{name}.csv": list(METHODS)}, "linear", x_label,
                "AP@0.5", title)


_PLOTTED = list(PLOTTED_GENERATION_METHODS)
#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare(
    "evaluate",
    data=("data/sim", "data/voxels", "artifacts/vqvae", "artifacts/adapt/source_vq", "artifacts/stage1",
          "artifacts/stage2", "artifacts/selftrain", "artifacts/fusion/models", "artifacts/fusion/training.json",
          "artifacts/ddpm/features"),
    params=("fusion", "ddpm", "stage1", "selftrain", "stage2", "voxelize", "simulate"),
    reports=("reports/generation_accuracy.md", "reports/gallery", "reports/plots", "reports/fusion.md"),
    images=("reports/fusion_pr.png", "reports/fusion_robustness.png"),
    plots=(
        Plot("iou_by_band", "range_m", {"reports/plots/iou_by_band.csv": _PLOTTED}, "linear",
             "range band centre (m from the sensor)", "IoU", "IoU to the truth by range band, held-out target pairs"),
        Plot("row_profile", "elevation_deg", {"reports/plots/row_profile.csv": ["truth", *_PLOTTED]},
             "linear", "beam elevation (deg)", "share of azimuth bins with a return",
             "range-image row occupancy of generated reference views, held-out target pairs"),
        Plot("fusion_pr", "recall",
             {"reports/plots/fusion_pr.csv": ["none_ego", *(f"{m}_{d}" for m in METHODS if m != "none"
                                                            for d in ("oracle", "generated"))]},
             "simple", "recall", "precision (interpolated)", "PR curves on real_cav/test, AP@0.5, all ranges (first seed)"),
        _sweep("position_std", "position_std_m", "position noise sigma (m)", "AP vs pose noise"),
        _sweep("heading_std", "heading_std_deg", "heading noise sigma (deg)", "AP vs heading noise"),
        _sweep("delay", "delay_ms", "time delay applied (ms)", "AP vs time delay"),
        _sweep("bits", "bits", "feature bits per value", "AP vs feature quantisation"),
    ))


def cell(v) -> str:
    return interval_cell(v, adaptive=True) if v is None or isinstance(v, Interval) else str(v)


def table(rows: dict[str, dict], columns: list[tuple[str, str]], first: str = "method") -> str:
    return markdown_table([first, *(h for _, h in columns)],
                          ([name, *(cell(values.get(k)) for k, _ in columns)] for name, values in rows.items()))


def comparisons(table_: dict[str, dict[str, Interval]], pairs: list[tuple[str, str, str]]) -> list[str]:
    """``A beats B on fig`` / ``does not beat`` lines from the intervals (higher is better, but
    lower where the figure's declaration says so: :data:`tasks.genscore.METRICS`, :mod:`tasks.realism`)."""
    lines = []
    for a, b, fig in pairs:
        if fig not in table_.get(a, {}) or fig not in table_.get(b, {}):
            continue
        x, y = table_[a][fig], table_[b][fig]
        lower = genscore.lower_is_better(fig) or realism.LOWER_IS_BETTER.get(fig, False)
        wins = (y.low > x.high) if lower else x.above(y)
        verdict = "**beats**" if wins else "does not beat"
        lines.append(f"- {gen.label(a)} {verdict} {gen.label(b)} on {fig}: {cell(x)} vs {cell(y)}")
    return lines


def write_generation_report(path: Path, result: dict, *, extra: list[str], gallery_md: str = "") -> Path:
    """``reports/generation_accuracy.md`` from :func:`tasks.evaluate_generation.run`'s result."""
    t = result["table"]
    rows = gen.report_rows(result)
    typ, resim_key = result["typ"], result["resim_key"]
    text = [
        "# Generated reference views against the truth (held-out simulated target scenes)", "",
        f"{result['pairs']} (ego, reference) pairs from {result['scenes']} held-out scenes; learned rows are "
        f"sampled once per training seed ({len(result['seeds'])} seed(s): {result['seeds']}). Each cell is the "
        "figure pooled over the pairs (mean over seeds) and its 95 % bootstrap interval over scenes and seeds, "
        "`value [low, high]`. IoU over all voxels; per band over the BEV cells at that distance from the "
        "reference sensor; seen / unseen: cells the ego's cloud did / did not cover; above ground: voxels more "
        "than 0.3 m over the true view's local ground. Object hit rate: labelled vehicles within 50 m of the "
        "reference sensor with at least 10 of the method's points in their box. Chamfer (m) over occupied voxel "
        "centres; JSD / MMD: BEV distances of the sets of occupied voxel centres, r2dm preset (MMD: point "
        "estimate, no interval).", "",
        table(rows, ACCURACY_COLUMNS), "",
        "Seconds per reference view: " + ", ".join(f"{gen.METHODS.get(k, k)} {v:.3f}"
                                                   for k, v in result["seconds"].items()) + ".", "",
        "## What beats what (intervals not overlapping)", "",
        *comparisons(t, [(typ, "naive_copy", "iou"), (typ, "stage1_only", "iou"), (typ, "naive_copy", "iou_above_ground"),
                         (resim_key, "resim", "iou"), *((resim_key, "resim", f"iou_{b}") for b in ("0-20", "20-40", "40-80")),
                         (resim_key, "resim", "iou_unseen"), (resim_key, "resim", "iou_above_ground"),
                         (typ, "no_adaptation", "jsd_r2dm"), ("disc_st_dummy", "one_stage", "jsd_r2dm"),
                         ("cast", "hybrid", "iou"), ("cast", "resim", "iou"),
                         *(("cast", "resim", f"iou_{b}") for b in ("0-20", "20-40", "40-80", "above_ground"))]), "",
        "## TYP Table 4 analogue: the adaptation ablation", "",
        table({gen.label(k): t[k] for k in (*TABLE4, *([typ] if typ not in TABLE4 else [])) if k in t},
              [("jsd_r2dm", "JSD ↓"), ("mmd_r2dm", "MMD ↓"), ("iou", "IoU ↑")]), "",
        *([] if any(k in t for k in TABLE4 if k != typ) else
          ["Only the model the switches name was trained: the other rows need `selftrain.ablation: true` "
           "(the `small` profile sets it).", ""]),
        "## TYP Table 5 analogue: two-stage against one-stage training at equal steps", "",
        table({gen.label(k): t[k] for k in ("disc_st_dummy", "disc", "one_stage") if k in t},
              [("jsd_r2dm", "JSD ↓"), ("mmd_r2dm", "MMD ↓"), ("iou", "IoU ↑")]), "",
        *([] if "one_stage" in t else
          ["No one-stage model was trained: it needs `stage2.one_stage: true` (the same steps as stage 1 + "
           "stage 2 together).", ""]),
        f"Sample-to-sample agreement of TYP (pooled IoU between two noise seeds of the same pairs): "
        f"{result['spread_iou']:.3f} (1 would mean the sample ignores its noise)." if result["spread_iou"] is not None
        else "", "",
        *realism_section(result), "",
        *extra, "",
        gallery_md,
    ]
    return write_text(path, "\n".join(text) + "\n") or path


REALISM_COLUMNS = realism.COLUMNS


def realism_section(result: dict) -> list[str]:
    """The scan-pattern realism table (:mod:`tasks.realism`) and what beats what in it."""
    r = result["realism"]
    rows = {"true reference scan": r["truth"], **{gen.label(k): r[k] for k in [*gen.METHODS, *r] if k in r and k != "truth"}}
    floor = result["realism_floor"]
    layout = result["layout"]
    missing = result.get("realism_missing")
    return [
        "## Scan pattern and realism (the same pairs, against the true reference scans)", "",
        f"On a beam: the share of a view's points within ±{realism.ON_BEAM_DEG}° of one of the reference LiDAR's "
        f"{layout.height} beam elevations, seen from the beam's origin. Row profile L1: per beam row of the sensor's "
        f"{layout.height} x {layout.width} range image, the share of azimuth bins with a return, averaged over the "
        "views; the mean absolute difference from the true scans' profile over rows (`reports/plots/row_profile.csv`). "
        "FRID† / FPVD†: Fréchet distances between the true and the generated views in the feature spaces of the "
        "range-image and voxel networks the `ddpm` stage trains (typ's own small networks, not LiDM's: compare "
        "rows of this table, not other papers' figures). Intervals: 95 % bootstrap over scenes and seeds.", "",
        table(rows, REALISM_COLUMNS), "",
        *([f"FRID / FPVD not scored: {missing}.", ""] if missing else []),
        *([f"Two halves of the true scans (alternate scenes) score FRID {floor['frid']:.3f}, FPVD {floor['fpvd']:.3f} "
           "against each other: the floor of a set of this size.", ""] if floor else []),
        *comparisons(r, [(k, "resim", fig) for k in ("cast", "hybrid") for fig, _ in REALISM_COLUMNS]),
    ]


def intervals_json(table_: dict[str, dict[str, Interval]]) -> dict:
    """``{method: {figure: {value, low, high}}}`` for metrics/evaluate.json (NaN as None)."""
    def clean(v: float):
        return None if not np.isfinite(v) else round(float(v), 6)

    return {m: {k: {kk: clean(vv) for kk, vv in iv.to_dict().items()} for k, iv in row.items()} for m, row in table_.items()}


def gallery_samples(data: "gen.EvalSet", result: dict, n: int) -> list[dict]:
    """The first ``n`` pairs as :func:`typ.viz.gallery` samples: x_e', TYP's view, truth, re-simulation."""
    typ = result["typ"]
    occ = result["samples"].get(typ)
    out = []
    for i in range(min(n, len(data))):
        gen_i = occ[i] if occ is not None else None
        scores = {}
        if gen_i is not None:
            tp = np.count_nonzero(gen_i & data.x_r[i])
            scores["IoU TYP"] = tp / max(np.count_nonzero(gen_i | data.x_r[i]), 1)
        r = data.resim[i] > 0.5
        scores["IoU re-sim"] = np.count_nonzero(r & data.x_r[i]) / max(np.count_nonzero(r | data.x_r[i]), 1)
        e = data.x_e[i] > 0.5
        scores["IoU copy"] = np.count_nonzero(e & data.x_r[i]) / max(np.count_nonzero(e | data.x_r[i]), 1)
        sample = {"name": f"{data.scenes[i]}_pair{i:03d}", "scores": scores, "boxes": data.boxes[i],
                  "x_e": e.transpose(1, 2, 0), "true": data.x_r[i].transpose(1, 2, 0), "resim": r.transpose(1, 2, 0)}
        if gen_i is not None:
            sample["generated"] = gen_i.transpose(1, 2, 0)
        out.append(sample)
    return out


def run(cfg, root: Path, *, run=None) -> StageResult:
    """Score everything the trained artifacts provide; write the reports, plots and gallery."""
    from tasks import adapt
    from tasks.voxel_data import load_views
    from tasks.vqvae import load_model as load_vqvae

    block = cfg.evaluate
    x_vq, y_encoder = load_vqvae(root / block.vqvae / "x"), load_vqvae(root / block.vqvae / "y")
    # adaptation (TYP Table 4's premise): how target-like source views look through the target decoder
    source_vq = load_vqvae(root / block.adapt / "source_vq", "adapt")
    store = root / block.voxels
    src = load_views(store, dataset=block.source_domain, split=block.source_split, ego_only=False)
    tgt = load_views(store, dataset=block.target_domain, split=block.target_split)
    adaptation = {"before": adapt.translation_scores(x_vq, x_vq, src, tgt),
                  "after": adapt.translation_scores(source_vq, x_vq, src, tgt)}
    before, after = adaptation["before"]["jsd_r2dm"], adaptation["after"]["jsd_r2dm"]
    adaptation["jsd_change"] = (after - before) / before if before else float("nan")
    extra = [
        "## Adaptation (source views through the target decoder, TYP §3.4)", "",
        f"JSD of source test views decoded by G_tgt against target test views (r2dm preset): before adaptation "
        f"(E_tgt) {before:.3f}, after (E_src) {after:.3f}: {100 * adaptation['jsd_change']:+.0f} % "
        f"(TYP Table 4: 0.26 -> 0.16, -38 %).", "",
    ]
    split_root = root / block.sim / block.target_domain / block.target_split
    reason = missing_truth(split_root)
    if reason is None:
        metrics, paths, lines = generation_section(cfg, root, x_vq, y_encoder, extra, run=run)
    else:
        LOG.warning("evaluate: generation accuracy not scored: %s", reason)
        metrics, paths, lines = skipped_generation(root, root / block.reports, reason, extra)
    metrics["adaptation"] = adaptation
    fusion_metrics, fusion_paths, fusion_lines = fusion_section(cfg, root)
    metrics["fusion"] = fusion_metrics
    novel_metrics, novel_paths, novel_lines = novel_view_section(cfg, root)
    if novel_metrics:
        metrics["novel_view"] = novel_metrics
    summary = "\n".join(["# typ evaluate", "", *lines, "", *fusion_lines, *novel_lines])
    return StageResult(metrics, [*paths, *fusion_paths, *novel_paths], summary)


#: where the real-scan section writes (inside the gallery, one of the stage's outputs)
NOVEL_VIEW = GALLERY / "novel_view"


def novel_view_section(cfg, root: Path) -> tuple[dict, list[Path], list[str]]:
    """Generated views scored against real scans of the drives params name (``evaluate.novel_view``,
    :mod:`tasks.novel_view`): per drive, the headline figures of each method and the report under
    ``reports/gallery/novel_view/<drive>/``. No drive named: nothing (``make run`` reads no real data)."""
    from tasks import novel_view, novel_view_report
    from typ.voxel import Grid

    block = cfg.evaluate.novel_view
    if not block.sequences:
        return {}, [], []
    generator, model = novel_view.trained_generator(root, cfg, cfg.evaluate.selftrain)
    g = cfg.voxelize.grid
    grid = Grid(g.x_range, g.y_range, g.z_range, g.shape)
    metrics, paths, lines = {}, [], ["## Real scans at other poses (LiDAR4D's F-score, all pairs)", ""]
    for drive in block.sequences:
        data_root = root / drive.root
        result = novel_view.run_benchmark(data_root, drive.sequence, sensor=drive.sensor or None,
                                          grid=grid, generator=generator, model=model,
                                          cast=cfg.generate.cast, frames=drive.frames, max_pairs=block.max_pairs,
                                          n_boot=cfg.evaluate.n_boot, seed=cfg.evaluate.seed, log=LOG.info)
        name = f"{data_root.resolve().name}_{drive.sequence}"
        paths += novel_view_report.write_report(result, root / NOVEL_VIEW / name, pictures=block.pictures)
        doc = novel_view_report.to_json(result)
        metrics[name] = {k: doc[k] for k in ("pairs", "methods", "differences", "ratios_to_map_oracle", "models",
                                             "pair_rule")}
        lines += [f"- {name}: " + ", ".join(f"{m} {cell(result.summary['methods'][m]['all']['fscore'])}"
                                            for m in result.methods)]
    return metrics, paths, lines


def missing_truth(split_root: Path) -> str | None:
    """Why generated views cannot be scored on the scenarios under ``split_root``, or None: scoring
    needs the true view of a second agent, which a real single-agent dataset does not have."""
    from typ.formats.opv2v import list_agents, list_scenarios

    if not any(len(list_agents(folder)) > 1 for folder in list_scenarios(split_root)):
        return (f"no scenario of {split_root.parent.name}/{split_root.name} has a second agent (single-agent scenes, "
                "as a real KITTI / nuScenes / Waymo target domain gives): there is no true reference view to score "
                "against")
    return None


def skipped_generation(root: Path, reports: Path, reason: str, extra: list[str]) -> tuple[dict, list[Path], list[str]]:
    """The generation section when it cannot be scored: the report says why, the band plot's
    columns are empty and the gallery folder is empty."""
    from typ import plots

    line = f"Generation accuracy not scored: {reason}."
    report = write_text(root / GENERATION_REPORT, "\n".join(
        ["# Generated reference views against the truth", "", line, "", *extra]) + "\n") or root / GENERATION_REPORT
    (root / GALLERY).mkdir(parents=True, exist_ok=True)
    bands = plots.bands(reports / "plots" / "iou_by_band.csv", genscore.BANDS,
                        {k: [float("nan")] * len(genscore.BANDS) for k in PLOTTED})
    return {"generation": {}, "generation_skipped": reason}, [report, bands], [line]


def generation_section(cfg, root: Path, x_vq, y_encoder, extra: list[str], *, run=None
                       ) -> tuple[dict, list[Path], list[str]]:
    """Generation accuracy on the held-out simulated target scenes: metrics, report files, summary lines."""
    from pipelines.typ.pipeline_typ import TYPPipeline
    from pipelines.typ.pipeline_typ import generator_dir
    from typ import plots
    from typ.sim.sensor import domain_spec
    from typ.viz import gallery

    block = cfg.evaluate
    reports = root / block.reports
    grid = cfg.voxelize.sensor_grid(block.target_domain)
    spec = domain_spec(block.target_domain, azimuth_step_deg=cfg.simulate.azimuth_step_deg).sensor
    generator = TYPPipeline.from_pretrained(generator_dir(root / block.selftrain, cfg.stage1.seed))
    data = gen.build_eval_set(root / block.sim / block.target_domain / block.target_split, grid, spec,
                              max_pairs=block.max_pairs or None)
    nets = realism.load_feature_nets(root / cfg.ddpm.out / "features")
    if isinstance(nets, str):
        LOG.warning("evaluate: FRID / FPVD of generated views not scored: %s", nets)
    result = gen.run(cfg, root, data, x_vq, y_encoder, generator.point_stats, n_boot=block.n_boot, feature_nets=nets)
    samples = gallery_samples(data, result, block.gallery)
    gallery_md = gallery(samples, root / GALLERY, grid, link_prefix="gallery/",
                         title="Generated reference views beside the truth") if samples else ""
    report = write_generation_report(root / GENERATION_REPORT, result, extra=extra, gallery_md=gallery_md)
    t = result["table"]
    bands = plots.bands(reports / "plots" / "iou_by_band.csv", genscore.BANDS,
                        {k: [t[k][f"iou_{genscore.band_label(*b)}"].value if k in t else float("nan")
                             for b in genscore.BANDS] for k in PLOTTED})
    profiles = result["row_profiles"]
    rows_csv = plots.write_table(reports / "plots" / "row_profile.csv", {
        "elevation_deg": [round(e, 4) for e in result["layout"].elevations_deg],
        **{k: profiles[k] for k in ("truth", *PLOTTED)}})
    metrics = {"pairs": result["pairs"], "scenes": result["scenes"], "seeds": result["seeds"],
               "generation": intervals_json(result["table"]), "spread_iou": result["spread_iou"],
               "realism": intervals_json(result["realism"]),
               "realism_truth_floor": {k: round(v, 6) for k, v in result["realism_floor"].items()},
               "seconds_per_view": {k: round(v, 4) for k, v in result["seconds"].items()}}
    if run is not None:
        rows = [{"method": gen.label(k), **{f: round(iv.value, 5) for f, iv in v.items()}}
                for k, v in result["table"].items()]
        run.log_table(rows, "generation_accuracy.json")
        from typ.viz import safe_name

        for s in samples[:4]:  # the gallery's own PNGs (drawing them again cost 2 s each)
            run.artifact(root / GALLERY / f"{safe_name(s['name'])}.png", "gallery")
    lines = comparisons(result["table"], [(result["typ"], "naive_copy", "iou"), (result["typ"], "stage1_only", "iou"),
                                          (result["resim_key"], "resim", "iou")])
    return metrics, [report, bands, rows_csv], lines


def fusion_section(cfg, root: Path) -> tuple[dict, list[Path], list[str]]:
    """The fusion benchmark scored on the networks the fusion stage saved: its metrics, report
    files and summary lines; without any saved network, the reason it was skipped (logged)."""
    from tasks import fusion_report, fusion_score

    block = cfg.fusion
    if not (root / block.out / "models").is_dir():
        reason = f"{block.out}/models does not exist (the fusion stage trains the networks)"
        LOG.warning("evaluate: fusion benchmark skipped: %s", reason)
        return {"skipped": reason}, [], [f"Fusion benchmark skipped: {reason}."]
    results = fusion_score.score_trained(block, root)
    paths = fusion_report.write_report(results, block, root / block.reports)
    paths += fusion_report.write_plot_data(results, root / block.reports / "plots")
    metrics = fusion_report.metrics_of(results)
    t1 = metrics["table1"]
    lines = ["## Collaborative detection (real_cav test, AP@0.5 overall)", ""]
    for method, rows in t1.items():
        for data, cell in rows.items():
            v = (cell or {}).get("ap50", {}).get("overall")
            if v:
                lines.append(f"- {method}, {data}: {v['value']:.2f} [{v['low']:.2f}, {v['high']:.2f}]")
    return metrics, paths, lines
