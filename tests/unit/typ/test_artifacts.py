"""Module folders (typ.artifacts): the round trip, and reuse by run key (ddpm, its feature nets)."""
import json

import pytest
import torch

from typ.artifacts import load_if_key, load_module, save_module
from typ.errors import TypError


def _linear(config: dict) -> torch.nn.Linear:
    return torch.nn.Linear(config["inputs"], config["outputs"])


def test_a_saved_module_comes_back_with_its_weights_and_extra_fields(tmp_path):
    torch.manual_seed(0)
    net = _linear({"inputs": 3, "outputs": 2})
    save_module(tmp_path, net, {"inputs": 3, "outputs": 2}, key="k1", seconds=1.5)
    assert json.loads((tmp_path / "config.json").read_text()) == {
        "config": {"inputs": 3, "outputs": 2}, "key": "k1", "seconds": 1.5}
    back, meta = load_module(tmp_path, _linear, "ddpm")
    assert not back.training and meta["seconds"] == 1.5
    assert torch.equal(back.weight, net.weight) and torch.equal(back.bias, net.bias)


def test_load_if_key_reuses_only_the_same_run(tmp_path):
    assert load_if_key(tmp_path / "none", _linear, "ddpm", "k1") is None
    net = _linear({"inputs": 3, "outputs": 2})
    save_module(tmp_path, net, {"inputs": 3, "outputs": 2}, key="k1")
    assert load_if_key(tmp_path, _linear, "ddpm", "k2") is None
    found = load_if_key(tmp_path, _linear, "ddpm", "k1")
    assert found is not None and torch.equal(found[0].weight, net.weight) and found[1]["key"] == "k1"


def test_load_if_key_retrains_an_older_layout_and_names_a_damaged_one(tmp_path):
    # a folder written before the config moved under "config": another key, so it is retrained
    (tmp_path / "config.json").write_text(json.dumps({"key": "old", "model": {"inputs": 3, "outputs": 2}}))
    assert load_if_key(tmp_path, _linear, "ddpm", "new") is None
    (tmp_path / "config.json").write_text('{"key": "new", "config": ')  # cut off mid-write
    with pytest.raises(TypError, match=r"config.json: file: expected a readable JSON config the ddpm stage writes"):
        load_if_key(tmp_path, _linear, "ddpm", "new")
    (tmp_path / "config.json").write_text(json.dumps({"key": "new", "config": {"inputs": 3, "outputs": 2}}))
    with pytest.raises(TypError, match=r"model.safetensors: file: expected trained weights \(run the ddpm stage"):
        load_if_key(tmp_path, _linear, "ddpm", "new")
