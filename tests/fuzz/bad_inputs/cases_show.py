"""Bad-input cases: typ show: the manifests of simulated and generated scenarios (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

from pathlib import Path
import json

from bad_inputs.make_corpus import Probe, billion_laughs, case, fifo, opv2v_scenario, write


def _show(folder: Path, out: Path):
    from tasks.show import ShowOptions, show
    from typ import viz
    from typ.voxel import TINY_GRID

    return lambda: show(folder, out, ShowOptions(grid=TINY_GRID, window=viz.Window(resolution=0.4), resim=False))


@case("show", "sim_job_azimuth_step_1e-5", "huge")
def _(d):
    from tasks.simulate import MANIFEST, ScenarioJob

    y = opv2v_scenario(d)
    job = ScenarioJob("target", "train", 0, 7, 1, 4, 1e-5, 70.0, 0.1)  # its key matches: anyone can compute one
    manifest = write(y.parent.parent / MANIFEST, json.dumps({"job": job.describe(), "key": job.key()}))
    return Probe(says=(str(manifest), "job.azimuth_step_deg", "a step in [0.05, 10] deg"),
                 call=_show(y.parent.parent, d / "out"), watch=y.parent.parent)


@case("show", "yaml_billion_laughs", "bomb")
def _(d):
    y = opv2v_scenario(d, billion_laughs())
    return Probe(says=(str(y), "YAML nodes, aliases expanded"), call=_show(y.parent.parent, d / "out"),
                 watch=y.parent.parent)


@case("show", "generated_agents_not_a_list", "wrong dtype")
def _(d):
    from tasks.generate import MANIFEST

    y = opv2v_scenario(d)
    manifest = write(y.parent.parent / MANIFEST, json.dumps({"generated_agents": 5}))  # TypeError before
    return Probe(says=(str(manifest), "generated_agents", "a list of agent folder names"),
                 call=_show(y.parent.parent, d / "out"))


@case("show", "manifest_is_a_fifo", "not a regular file")
def _(d):
    from tasks.generate import MANIFEST

    y = opv2v_scenario(d)
    manifest = fifo(y.parent.parent / MANIFEST)
    return Probe(says=(str(manifest), "a readable JSON file", "FIFO"), call=_show(y.parent.parent, d / "out"),
                 watch=y.parent.parent)
