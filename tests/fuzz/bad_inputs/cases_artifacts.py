"""Bad-input cases: trained artifacts (safetensors + JSON, config.json, pipeline.json) (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

from pathlib import Path
import json

from typ.voxel import Grid

from bad_inputs.make_corpus import Probe, _tiny_unet, case, sparse


# One small model of each kind is saved as its stage saves it, then damaged; loading it as the
# next stage does must name the file and the stage that makes it. torch is imported inside.


def _tiny_vqvae():
    import torch

    from models.vqvae import BEVVQVAE

    torch.manual_seed(0)
    return BEVVQVAE(in_channels=4, latent_channels=3, block_out_channels=(8, 8), num_codes=8, norm_num_groups=4)




@case("artifact", "vqvae_truncated_weights", "truncated", needs="torch")
def _(d):
    from tasks.vqvae import load_model, save_model

    save_model(_tiny_vqvae(), d / "x")
    w = d / "x" / "model.safetensors"
    w.write_bytes(w.read_bytes()[:-100])
    return Probe(says=(str(w), "safetensors", "vqvae stage"), call=lambda: load_model(d / "x"))


@case("artifact", "stage1_missing_config", "missing keys", needs="torch")
def _(d):
    from tasks import stage1
    from typ.config import config_from_dict

    cfg = config_from_dict({}).stage1
    stage1.save_model(_tiny_unet(), cfg, {"low": 0.5, "high": 0.5, "noise_std": 0.0}, d / "seed_0")
    (d / "seed_0" / "config.json").unlink()
    return Probe(says=(str(d / "seed_0" / "config.json"), "missing", "stage1 stage"),
                 call=lambda: stage1.load_model(d / "seed_0"))


@case("artifact", "adapter_wrong_shape", "misaligned", needs="torch")
def _(d):
    from safetensors.torch import load, save

    from tasks import stage2

    unet = _tiny_unet()
    stage2.save_adapter(stage2.build_adapter(unet, res_blocks=1, seed=0), d / "adapter")
    w = d / "adapter" / "model.safetensors"
    state = load(w.read_bytes())
    name = sorted(state)[0]
    state[name] = state[name].reshape(-1)[:1].clone()  # one tensor of another shape
    w.write_bytes(save(state))
    return Probe(says=(str(w), f"weights.{name}", "shape", "stage2 stage"), call=lambda: stage2.load_adapter(d / "adapter"))


@case("artifact", "detector_corrupt_config", "unknown", needs="torch")
def _(d):
    from typ.artifacts import load_module

    (d / "early").mkdir()
    (d / "early" / "config.json").write_text('{"config": {"method": "early", ')  # cut off mid-write
    return Probe(says=(str(d / "early" / "config.json"), "JSON", "fusion stage"),
                 call=lambda: load_module(d / "early", lambda c: None, "fusion"))


@case("artifact", "checkpoint_truncated", "truncated", needs="torch")
def _(d):
    from tasks.training import load_latest, save_checkpoint

    path = save_checkpoint(d / "run", 4, {"model": _tiny_vqvae().state_dict()})
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    return Probe(says=(str(path), "complete training checkpoint"), call=lambda: load_latest(d / "run"))


@case("artifact", "checkpoint_with_code", "unknown", needs="torch")
def _(d):
    import io
    import pickle

    from tasks.training import load_latest

    (d / "run").mkdir()
    path = d / "run" / "step_00000004.pt"
    buf = io.BytesIO()
    pickle.dump({"step": 4, "hook": print}, buf)  # a pickle that would call code when loaded
    path.write_bytes(buf.getvalue())
    return Probe(says=(str(path), "tensors and numbers only"), call=lambda: load_latest(d / "run"))


@case("artifact", "generator_missing_thresholds", "missing keys", needs="torch")
def _(d):
    import json as json_

    from models.vqvae import PooledBoxMap
    from pipelines.typ.pipeline_typ import TYPPipeline

    grid = Grid((-6.4, 6.4), (-6.4, 6.4), (-0.75, 3.25), (16, 16, 4))
    pipe = TYPPipeline(_tiny_vqvae(), PooledBoxMap(downsample=2), _tiny_unet(), None, grid, "linear", 1000, "ddim",
                       2, {"low": 0.5, "high": 0.5, "noise_std": 0.0})
    pipe.save_pretrained(d / "generator")
    meta = d / "generator" / "pipeline.json"
    doc = json_.loads(meta.read_text())
    del doc["thresholds"]
    meta.write_text(json_.dumps(doc))
    return Probe(says=(str(meta), "selftrain stage", "thresholds"), call=lambda: TYPPipeline.from_pretrained(d / "generator"))




@case("artifact", "vqvae_config_huge_sizes", "huge", needs="torch")
def _(d):
    from tasks.vqvae import load_model, save_model

    save_model(_tiny_vqvae(), d / "x")
    path = d / "x" / "config.json"
    doc = json.loads(path.read_text())
    doc["config"]["block_out_channels"] = [100_000, 100_000]  # 360 GB of convolution weights before
    path.write_text(json.dumps(doc))
    return Probe(says=(str(path), "config.block_out_channels", "vqvae stage"), call=lambda: load_model(d / "x"))


@case("artifact", "vqvae_config_zero_groups", "wrong units", needs="torch")
def _(d):
    from tasks.vqvae import load_model, save_model

    save_model(_tiny_vqvae(), d / "x")
    path = d / "x" / "config.json"
    doc = json.loads(path.read_text())
    doc["config"]["norm_num_groups"] = 0  # ZeroDivisionError before
    path.write_text(json.dumps(doc))
    return Probe(says=(str(path), "config", "ZeroDivisionError"), call=lambda: load_model(d / "x"))


@case("artifact", "weights_sparse_4_gib", "huge", needs="torch")
def _(d):
    from tasks.vqvae import load_model, save_model

    save_model(_tiny_vqvae(), d / "x")
    w = d / "x" / "model.safetensors"
    sparse(w, 4 << 30, w.read_bytes())  # read whole before any check: MemoryError
    return Probe(says=(str(w), "of at most 1024 MiB", str(4 << 30)), call=lambda: load_model(d / "x"))


@case("artifact", "weights_header_offsets_past_the_end", "truncated", needs="torch")
def _(d):
    from tasks.vqvae import load_model, save_model

    save_model(_tiny_vqvae(), d / "x")
    w = d / "x" / "model.safetensors"
    raw = w.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    header = json.loads(raw[8:8 + n])
    name = sorted(k for k in header if k != "__metadata__")[0]
    header[name]["data_offsets"][1] += 4 << 30  # a tensor claimed to span 4 GiB more
    text = json.dumps(header).encode()
    w.write_bytes(len(text).to_bytes(8, "little") + text + raw[8 + n:])
    return Probe(says=(str(w), f"header.{name}", "data_offsets"), call=lambda: load_model(d / "x"))


def _generator(d: Path, **changes) -> Probe:
    import json as json_

    from models.vqvae import PooledBoxMap
    from pipelines.typ.pipeline_typ import TYPPipeline

    grid = Grid((-6.4, 6.4), (-6.4, 6.4), (-0.75, 3.25), (16, 16, 4))
    pipe = TYPPipeline(_tiny_vqvae(), PooledBoxMap(downsample=2), _tiny_unet(), None, grid, "linear", 1000, "ddim",
                       2, {"low": 0.5, "high": 0.5, "noise_std": 0.0})
    pipe.save_pretrained(d / "generator")
    meta = d / "generator" / "pipeline.json"
    doc = json_.loads(meta.read_text())
    doc.update(changes)
    meta.write_text(json_.dumps(doc))
    return Probe(says=(str(meta),), call=lambda: TYPPipeline.from_pretrained(d / "generator"))


@case("artifact", "generator_grid_of_a_trillion_voxels", "huge", needs="torch")
def _(d):
    probe = _generator(d, grid={"x_range": [-6.4, 6.4], "y_range": [-6.4, 6.4], "z_range": [-0.75, 3.25],
                                "shape": [100_000, 100_000, 100]})
    probe.says += ("shape", "at most 67108864 voxels")
    return probe


@case("artifact", "generator_thresholds_reversed", "wrong units", needs="torch")
def _(d):
    probe = _generator(d, thresholds={"low": 0.9, "high": 0.1, "noise_std": 0.0})
    probe.says += ("thresholds", "0 <= low <= high <= 1")
    return probe
