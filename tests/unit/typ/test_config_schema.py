"""params.schema.json: the committed schema is the one the config classes give, it accepts every
profile's values and params.yaml, and it rejects what the loader rejects for structure or type."""
from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import pytest
import yaml

from typ.config import PROFILES, as_dict, config_from_dict, load_config, profile_defaults
from typ.config_schema import SCHEMA_FILE, config_schema
from typ.errors import TypError
from repo_paths import REPO

ROOT = REPO


@pytest.fixture(scope="module")
def validator():
    schema = config_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_the_committed_schema_is_the_generated_one():
    committed = json.loads((ROOT / SCHEMA_FILE).read_text())
    assert committed == json.loads(json.dumps(config_schema())), f"stale {SCHEMA_FILE}: run `typ schema`"
    assert (ROOT / "params.yaml").read_text().splitlines()[0] == f"# yaml-language-server: $schema={SCHEMA_FILE}"


@pytest.mark.parametrize("profile", PROFILES)
def test_every_profile_and_params_yaml_validate(validator, profile):
    validator.validate({"profile": profile, **profile_defaults(profile)})
    # the values in effect, as typ check prints them: every key the loader knows is in the schema
    cfg = config_from_dict({"profile": profile})
    validator.validate({"profile": profile, **{s: as_dict(getattr(cfg, s)) for s in
                                               ("tracking", "runtime", "serve", *cfg.STAGES)}})
    validator.validate(yaml.safe_load((ROOT / "params.yaml").read_text()))


BAD = {
    "unknown key": ({"voxelize": {"gird": {}}}, "voxelize.gird"),
    "wrong type": ({"simulate": {"frames": "two"}}, "simulate.frames"),
    "bool for an integer": ({"simulate": {"frames": True}}, "simulate.frames"),
    "unknown profile": ({"profile": "huge"}, "profile"),
    "wrong length": ({"voxelize": {"grid": {"shape": [128, 128]}}}, "voxelize.grid.shape"),
    "unknown choice": ({"runtime": {"device": "tpu"}}, "runtime.device"),
    "list item missing a key": ({"generate": {"sets": [{"dataset": "target"}]}}, "generate.sets[0]"),
}


@pytest.mark.parametrize("case", BAD, ids=list(BAD))
def test_what_the_loader_rejects_for_structure_or_type_the_schema_rejects(validator, case, tmp_path):
    raw, field = BAD[case]
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(TypError) as info:
        load_config(path)
    assert field in str(info.value)
    assert not validator.is_valid(raw), f"the schema accepts {raw}"
