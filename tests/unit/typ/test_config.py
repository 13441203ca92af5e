"""params.yaml -> typed config: defaults per profile, overrides, and named errors."""
import pytest
import yaml

from typ import config
from typ.config import config_from_dict, flatten, load_config, profile_defaults
from typ.errors import TypError


def test_repo_params_load_with_tiny_profile():
    cfg = load_config("params.yaml")
    assert cfg.profile == "tiny"
    assert cfg.voxelize.grid.shape == (128, 128, 8)
    assert cfg.simulate.agents_min >= 1


def test_paper_profile_carries_the_papers_grid():
    cfg = config_from_dict({"profile": "paper"})
    g = cfg.voxelize.grid
    assert g.shape == (512, 512, 20)
    assert g.x_range == (-51.2, 51.2) and g.y_range == (-51.2, 51.2)
    assert g.z_range[1] - g.z_range[0] == pytest.approx(4.0)
    # 0.2 m voxels in every axis, as in TYP §4
    assert (g.x_range[1] - g.x_range[0]) / g.shape[0] == pytest.approx(0.2)
    assert (g.z_range[1] - g.z_range[0]) / g.shape[2] == pytest.approx(0.2)


def test_override_is_key_by_key_and_keeps_other_defaults():
    cfg = config_from_dict({"profile": "tiny", "simulate": {"frames": 7, "scenarios": {"target": {"test": 5}}}})
    tiny = profile_defaults("tiny")["simulate"]
    assert cfg.simulate.frames == 7
    assert cfg.simulate.scenarios["target"]["test"] == 5
    assert cfg.simulate.scenarios["target"]["train"] == tiny["scenarios"]["target"]["train"]
    assert cfg.simulate.seed == tiny["seed"]


@pytest.mark.parametrize("raw, field, expected", [
    ({"profile": "huge"}, "profile", "one of ['tiny', 'small', 'paper']"),
    ({"simulate": {"frames": "3"}}, "simulate.frames", "an integer"),
    ({"simulate": {"frame": 3}}, "simulate.frame", "known keys"),
    ({"simulate": {"frames": 0}}, "simulate.frames", "an integer in [1, 10000]"),
    ({"simulate": {"agents_min": 4, "agents_max": 2}}, "simulate.agents_min/agents_max", "agents_min <= agents_max"),
    ({"simulate": {"scenarios": {"mars": {"train": 1}}}}, "simulate.scenarios.mars", "sensor domain"),
    ({"simulate": {"scenarios": {"target": {"train": -1}}}}, "simulate.scenarios.target.train", "in [0, 100000]"),
    ({"voxelize": {"grid": {"shape": [128, 0, 8]}}}, "voxelize.grid.shape[1]", "an integer in [1, 8192]"),
    ({"voxelize": {"grid": {"shape": [128, 8]}}}, "voxelize.grid.shape", "a list of 3"),
    ({"voxelize": {"grid": {"x_range": [5.0, -5.0]}}}, "voxelize.grid.x_range", "min < max"),
    ({"voxelize": {"grid": {"z_range": [0, ".nan"]}}}, "voxelize.grid.z_range[1]", "a number"),
    ({"voxelize": {"workers": True}}, "voxelize.workers", "an integer"),
    ({"tracking": {"experiment": ""}}, "tracking.experiment", "non-empty"),
    ({"voxelize": 3}, "voxelize", "a mapping"),
    ({"stage1": {"ego_only": "no"}}, "stage1.ego_only", "true or false"),
    ({"selftrain": {"adapter_scale": 0.0}}, "selftrain.adapter_scale", "a number in (0, 1000]"),
])
def test_bad_values_name_the_dotted_field(raw, field, expected):
    with pytest.raises(TypError) as info:
        config_from_dict(raw, where="params.yaml")
    err = info.value
    assert err.field == field
    assert expected in err.expected
    assert str(err).startswith("params.yaml: " + field)


def test_bad_yaml_and_missing_file_are_named(tmp_path):
    bad = tmp_path / "params.yaml"
    bad.write_text("simulate: [unclosed\n")
    with pytest.raises(TypError, match="params.yaml: yaml: expected well-formed YAML"):
        load_config(bad)
    with pytest.raises(TypError, match="file: expected a params.yaml"):
        load_config(tmp_path / "absent.yaml")
    bad.write_text("- a\n- b\n")
    with pytest.raises(TypError, match="<top level>"):
        load_config(bad)


def test_flatten_gives_dotted_names():
    cfg = config_from_dict({})
    flat = flatten(cfg.voxelize)
    assert flat["grid.shape"] == [128, 128, 8]
    assert flat["grid.x_range"] == [-51.2, 51.2]
    assert "workers" in flat


def test_every_profile_loads_and_has_the_same_keys():
    from typ.config import as_dict

    profiles = yaml.safe_load(open("typ/profiles.yaml"))
    assert set(profiles) == {"tiny", "small", "paper"} and profiles["small"]["extends"] == "tiny"

    def keys(d):  # scenario counts per split and per-domain lengths may differ between profiles
        return {k for k in flatten(d) if not k.startswith(("simulate.scenarios", "simulate.domains"))}

    assert keys(profiles["tiny"]) == keys(profiles["paper"])
    for profile in profiles:
        config_from_dict({"profile": profile})
    # small inherits what it does not set, and overrides what it sets
    tiny, small = as_dict(config_from_dict({"profile": "tiny"})), as_dict(config_from_dict({"profile": "small"}))
    assert small["stage1"]["replicas"] == 3 and small["stage1"]["unet"] == tiny["stage1"]["unet"]
    assert small["vqvae"]["x"]["epochs"] == 30 and small["vqvae"]["x"]["block_out_channels"] == tiny["vqvae"]["x"]["block_out_channels"]
    assert profile_defaults("small")["voxelize"] == profile_defaults("tiny")["voxelize"]


def test_per_domain_lengths_are_replaced_whole_by_params(monkeypatch):
    tiny = config_from_dict({}).simulate
    assert tiny.for_domain("target") == (2, 3, 3)              # the profile's target scenes
    flat = config_from_dict({"simulate": {"domains": {}, "frames": 5, "agents_min": 2, "agents_max": 2}}).simulate
    assert flat.domains == {} and flat.for_domain("target") == flat.for_domain("source") == (5, 2, 2)
    one = config_from_dict({"simulate": {"domains": {"source": {"frames": 3, "agents_min": 2, "agents_max": 2}}}})
    assert set(one.simulate.domains) == {"source"}              # not merged with the profile's target entry
    # a profile that extends another refines its per-domain lengths instead
    profiles = yaml.safe_load(open("typ/profiles.yaml"))
    profiles["small"] = {"extends": "tiny", "simulate": {"domains": {"real_cav": {"frames": 8}}}}
    monkeypatch.setattr(config, "_profiles", lambda: profiles)
    domains = profile_defaults("small")["simulate"]["domains"]
    assert set(domains) == {"source", "target", "real_cav"} and domains["target"] == profiles["tiny"]["simulate"]["domains"]["target"]
    assert domains["real_cav"] == {"frames": 8}


def test_small_profile_is_tiny_with_the_generators_seeds_and_table_rows():
    tiny, small = config_from_dict({"profile": "tiny"}), config_from_dict({"profile": "small"})
    assert small.stage1.replicas == 3 and tiny.stage1.replicas == 1 and small.stage1.unet == tiny.stage1.unet
    assert small.stage2.one_stage and small.selftrain.ablation and not (tiny.stage2.one_stage or tiny.selftrain.ablation)
    assert (small.vqvae.x.gamma, small.vqvae.x.epochs) == (2.0, 30) and small.vqvae.x.num_codes == tiny.vqvae.x.num_codes
    # the data, the detectors and the SSC networks are tiny's: small only adds generator work
    assert (small.simulate, small.fusion, small.ssc) == (tiny.simulate, tiny.fusion, tiny.ssc)
