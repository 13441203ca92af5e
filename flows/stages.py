"""The pipeline's stages as declared beside their code: what each reads, writes and draws.

Each stage's task module ``tasks/<name>.py`` holds its ``DECLARATION``
(:func:`typ.registry.declare`: data and artifact deps, params blocks, outputs, reports, figures);
:data:`typ.registry.STAGES` holds the order and each stage's kind. ``dvc.yaml`` is generated from
the declarations (``typ dvc-yaml``, :mod:`flows.dvcyaml`; a test fails when the committed file
differs), with each stage's code deps taken from its flow's import closure and its profile keys
from ``typ/profiles.yaml``.

Adding a stage is a task module ``tasks/<name>.py`` with its ``DECLARATION`` and its name and kind
in :data:`typ.registry.STAGES`, plus its config block: a stage with no flow module of its own runs
through :mod:`flows.generic` (the task module's ``scene_stage`` or ``run``).

Collecting the declarations imports every stage's task module (torch too): dvc.yaml's generation
and its tests do; the runner reads kinds from :data:`typ.registry.STAGES` alone. No stage's flow
imports this module, so it is no stage's code dep.
"""
from __future__ import annotations

import importlib
import importlib.util

from typ.errors import TypError
from typ.registry import STAGES, Plot, Stage

__all__ = ["BENCH_PLOTS", "Plot", "Stage", "by_name", "stages"]


def _declaration(name: str) -> Stage:
    where = f"tasks/{name}.py"
    if importlib.util.find_spec(f"tasks.{name}") is None:
        raise TypError(where, "module", f"the task module of stage {name!r} (typ.registry.STAGES)", "missing")
    declared = getattr(importlib.import_module(f"tasks.{name}"), "DECLARATION", None)
    if not isinstance(declared, Stage) or declared.name != name:
        raise TypError(where, "DECLARATION", f"typ.registry.declare({name!r}, ...)",
                       getattr(declared, "name", type(declared).__name__))
    return declared


def stages() -> tuple[Stage, ...]:
    """Every stage's declaration in the order ``dvc repro`` runs them, :data:`typ.registry.STAGES`'."""
    return tuple(_declaration(name) for name in STAGES)


def by_name() -> dict[str, Stage]:
    """Every stage by name, in pipeline order."""
    return {s.name: s for s in stages()}


#: plots of files no stage writes (``make bench``)
BENCH_PLOTS = (
    Plot("reports/bench_sampling.csv", "seconds", "error", "scatter", "seconds per sample",
         "1 - voxel IoU to the truth", "stage-1 samplers x steps x schedules, time against error"),
)
