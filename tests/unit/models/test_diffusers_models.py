"""typ's diffusers-like networks are diffusers models: ``ModelMixin`` + ``ConfigMixin`` with the
constructor's arguments registered, so ``save_pretrained`` / ``from_pretrained`` round-trip them
(weights, buffers and config) as they do a ``UNet2DModel``, beside typ's own artifact format."""
import json

import pytest
import torch
from diffusers import ConfigMixin, ModelMixin

from models.adapter import ZeroAdapter
from models.discriminator import LatentDiscriminator
from models.ldm import LatentDiffusion
from models.lidar_features import SegmentationFeatureNet
from models.pixel_ddpm import PixelDiffusion
from typ.artifacts import load_module, save_module


def _ldm():
    m = LatentDiffusion(latent_channels=4, cond_channels=3, sample_size=8, block_out_channels=(8, 16),
                        norm_num_groups=4, cross_attention_dim=8, attention_head_dim=4, time_embedding="fourier",
                        coordinates=True)
    m.set_statistics(torch.randn(6, 4, 8, 8) * 3 + 1, torch.randn(6, 3, 8, 8))   # buffers that must travel
    return m, lambda: (torch.randn(2, 4, 8, 8), torch.tensor([3, 7]), torch.randn(2, 3, 8, 8))


MODELS = {
    "adapter": (lambda: ZeroAdapter(latent_channels=4, channels=(8, 16), conditions=2),
                lambda: (torch.randn(2, 8, 8, 8),)),
    "ldm": None,
    "pixel": (lambda: PixelDiffusion(channels=2, height=8, width=16, patch=(1, 2), block_out_channels=(8, 16),
                                     norm_num_groups=4, dropout=0.0, time_embedding="fourier", coordinates=True),
              lambda: (torch.randn(2, 2, 8, 16), torch.tensor([1, 500]))),
    "discriminator": (lambda: LatentDiscriminator(in_channels=4, width=8), lambda: (torch.randn(2, 4, 8, 8),)),
    "features": (lambda: SegmentationFeatureNet(in_channels=2, out_channels=3, width=4, levels=2),
                 lambda: (torch.randn(2, 2, 8, 8),)),
}


def _build(name):
    torch.manual_seed(0)
    if name == "ldm":
        return _ldm()
    make, inputs = MODELS[name]
    return make(), inputs


def _outputs(model, args):
    with torch.no_grad():
        out = model.eval()(*args)
    return out if isinstance(out, list) else [out]


@pytest.mark.parametrize("name", list(MODELS))
def test_save_pretrained_and_from_pretrained_round_trip(name, tmp_path):
    model, inputs = _build(name)
    assert isinstance(model, ModelMixin) and isinstance(model, ConfigMixin)
    if name == "adapter":   # zero convolutions: make the outputs say something
        for conv in model.zero:
            torch.nn.init.normal_(conv.weight)
    model.save_pretrained(tmp_path)
    again = type(model).from_pretrained(tmp_path, low_cpu_mem_usage=False)
    public = json.loads(json.dumps({k: v for k, v in model.config.items() if not k.startswith("_")}))
    assert json.loads(json.dumps({k: again.config[k] for k in public})) == public
    state, loaded = model.state_dict(), again.state_dict()
    assert state.keys() == loaded.keys() and all(torch.equal(state[k], loaded[k]) for k in state)
    torch.manual_seed(1)
    args = inputs()
    for a, b in zip(_outputs(model, args), _outputs(again, args)):
        assert torch.equal(a, b)


@pytest.mark.parametrize("name", list(MODELS))
def test_typs_artifact_keeps_the_constructor_arguments_and_not_diffusers_bookkeeping(name, tmp_path):
    model, _ = _build(name)
    save_module(tmp_path, model, model.config, key="k")
    written = json.loads((tmp_path / "config.json").read_text())["config"]
    assert written and not any(k.startswith("_") for k in written)
    again, meta = load_module(tmp_path, type(model).from_config, "test")
    assert meta["key"] == "k" and all(torch.equal(a, b) for a, b in zip(model.state_dict().values(),
                                                                        again.state_dict().values()))
