"""What a stage's task module hands its flow, without Prefect: a per-scene stage's pieces
(:class:`SceneStage`, run by ``flows.common``), or the other stages' result (:class:`StageResult`).

Building one reads the params and lists the scenes but imports no orchestration, so the CLI can
settle a stage whose every scene is unchanged before Prefect is imported
(``flows.common.settle_unchanged``), and the stage's flow runs the same pieces otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable


@dataclass(frozen=True)
class SceneStage:
    """``plan()`` gives the items to do and the stale outputs: what lies where the stage's outputs
    go but is no output of the current plan: only those the stage wrote (its record,
    :func:`typ.io.written_by`) are deleted, the others are left alone and counted; ``work(item, **work_kwargs)`` makes one item's output and returns
    a dict with ``scenario`` and ``skipped`` (None or the reason); ``unchanged(item,
    **work_kwargs)`` is the cheap check ``work`` starts with (the skipped result of an item whose
    stored output is current, else None); ``summarize(results)`` gives the stage's metrics;
    ``label(item)`` names an item in logs and task names."""

    out: Path
    plan: Callable[[], tuple[list, list[Path]]]
    work: Callable[..., dict]
    label: Callable[[object], str]
    summarize: Callable[[list[dict]], dict]
    work_kwargs: dict = field(default_factory=dict)
    unchanged: Callable[..., dict | None] | None = None


@dataclass
class StageResult:
    """What a stage's ``run`` returns (``flows.generic``): its metrics (``metrics/<stage>.json``),
    the files its MLflow run keeps (paths, or (path, folder) pairs) and a markdown summary for
    the Prefect UI ("" for none)."""

    metrics: dict
    artifacts: list = field(default_factory=list)
    summary: str = ""
