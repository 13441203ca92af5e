"""``typ novel-view``: the real-scan benchmark of one drive (:mod:`tasks.novel_view`), with the
trained generator when ``make run`` has made one, written by :mod:`tasks.novel_view_report`."""
from __future__ import annotations

import logging
from pathlib import Path

from tasks import novel_view, novel_view_report
from typ.config import load_config
from typ.errors import TypError

LOG = logging.getLogger(__name__)


def run_novel_view(fmt: str, input_path: Path, out: Path, *, root: Path, params: str, sequence: str | None = None,
                   sensor: str | None = None, methods: list[str] | None = None, max_pairs: int = 0,
                   frames: tuple[int, int] | None = None, pictures: bool = True) -> novel_view.BenchmarkResult:
    """Score every pair of drive ``sequence`` (default: the only one) of the dataset at ``input_path``
    and write ``out/novel_view.json``, ``out/novel_view.md`` and the pictures."""
    from typ.formats.kitti_odometry import list_sequences
    from tasks.ingest import ODOMETRY
    from tasks.voxelize import to_grid

    if fmt != ODOMETRY:
        raise TypError("typ novel-view", "--format", f"{ODOMETRY} (a drive whose every scan has its pose)", fmt)
    if not Path(input_path).is_dir():
        raise TypError(input_path, "--input", "a dataset folder in the KITTI odometry layout (sequences/<seq>/)",
                       "not a folder")
    if sequence is None:
        found = list_sequences(input_path)
        if len(found) != 1:
            raise TypError(input_path, "--sequence", f"one of the sequences found ({found or 'none'})", None)
        sequence = found[0]
    cfg = load_config(root / params)
    learned = any(novel_view.METHODS[m].learned for m in (methods or novel_view.METHODS) if m in novel_view.METHODS)
    generator, model = (novel_view.trained_generator(root, cfg) if learned
                        else (None, "none (no learned method asked for)"))
    if generator is None:
        LOG.warning("typ novel-view: the learned methods are skipped: %s", model)
    result = novel_view.run_benchmark(Path(input_path), sequence, sensor=sensor, grid=to_grid(cfg.voxelize.grid),
                                      generator=generator, model=model, cast=cfg.generate.cast, methods=methods,
                                      frames=frames, max_pairs=max_pairs, n_boot=cfg.evaluate.n_boot,
                                      seed=cfg.generate.seed, log=LOG.info)
    novel_view_report.write_report(result, out, pictures=pictures)
    return result
