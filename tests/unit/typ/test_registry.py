"""typ.registry: one torch-free home below the config for the names the config offers; the code
that runs an entry reads it from there (property tests, not copies held equal)."""
import importlib.machinery
import subprocess
import sys

import numpy as np
import pytest

from typ.registry import COMPOSE_MODES, SCHEDULES


def test_the_registry_and_the_config_import_nothing_above_typ():
    """The config's names come from typ.registry, which loads no torch, numpy, models or tasks:
    ``typ check`` and the params schema stay fast, and no import runs up a layer."""
    code = ("import sys, typ.config, typ.registry; "
            "up = sorted(m for m in sys.modules if m.split('.')[0] in {'torch', 'diffusers', 'models', 'tasks', 'flows', 'pipelines'}); "
            "assert not up, up[:5]")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


@pytest.mark.parametrize("name", list(SCHEDULES))
def test_every_schedule_names_a_beta_function_that_gives_a_schedule(name):
    from models.schedules import SCHEDULES as FUNCTIONS, alphas_cumprod, betas

    assert FUNCTIONS[name].__name__ == SCHEDULES[name].function
    b = betas(name, 50)
    assert b.shape == (50,) and b.dtype == np.float64 and ((b > 0) & (b < 1)).all()
    assert (np.diff(alphas_cumprod(b)) < 0).all()


def test_compose_modes_reach_every_command_that_takes_one():
    from tasks.edit import COMPOSE as EDITABLE
    from tasks.fusion_report import COMPOSE_TEXT
    from typ.config import COMPOSE, config_from_dict

    assert COMPOSE == tuple(COMPOSE_MODES) and set(EDITABLE) <= set(COMPOSE)
    assert EDITABLE == tuple(n for n, m in COMPOSE_MODES.items() if m.editable) and "generated" in EDITABLE
    assert all(COMPOSE_TEXT[n] == m.text and m.text for n, m in COMPOSE_MODES.items())
    for name in COMPOSE_MODES:   # every mode is a value params.yaml may give
        assert config_from_dict({"profile": "tiny", "generate": {"compose": name}}).generate.compose == name


def test_the_stage_list_is_the_registrys_and_a_stage_without_a_declaration_is_named(monkeypatch):
    """One ordered stage list: the config's and dvc.yaml's follow typ.registry.STAGES, kinds
    included; each stage's declaration sits in its task module. A registered stage without a task
    module or a DECLARATION, or a module declaring another stage, is a named error, not a
    pipeline that silently lacks it."""
    import types

    import tasks
    from flows import stages
    from typ.config import Config
    from typ.errors import TypError
    from typ.registry import STAGES, StageSpec, declare

    declared = stages.stages()
    assert Config.STAGES == tuple(STAGES) == tuple(s.name for s in declared)
    assert all((s.kind, s.torch) == (STAGES[s.name].kind, STAGES[s.name].torch) for s in declared)
    monkeypatch.setitem(STAGES, "density", StageSpec("scoring", torch=False))
    with pytest.raises(TypError, match=r"tasks/density.py.*module.*missing"):
        stages.stages()
    module = types.ModuleType("tasks.density")
    monkeypatch.setitem(sys.modules, "tasks.density", module)
    monkeypatch.setattr(tasks, "density", module, raising=False)
    module.__spec__ = importlib.machinery.ModuleSpec("tasks.density", None)
    with pytest.raises(TypError, match=r"tasks/density.py.*DECLARATION"):
        stages.stages()
    module.DECLARATION = declare("simulate")
    with pytest.raises(TypError, match=r"tasks/density.py.*DECLARATION.*simulate"):
        stages.stages()
    module.DECLARATION = declare("density", data=("data/sim",))
    assert stages.by_name()["density"].data == ("data/sim",) and stages.stages()[-1].kind == "scoring"
    with pytest.raises(TypError, match=r"typ.registry.STAGES.*nowhere"):
        declare("nowhere")
