"""The ddpm stage's parts: model, config, training (resume, reuse, NaN guard), sampling, metrics, targets."""
import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from models.pixel_ddpm import PixelDiffusion, fold, unfold
from models.time_embedding import FourierTimeEmbedding
from tasks import ddpm as stage
from tasks.ddpm_metrics import score, set_stats
from tasks import ddpm_report
from tasks.ddpm_report import targets
from tasks.training import prediction_target
from tasks.lidar_features import FeatureNets, build as build_net, voxel_labels
from tasks.training import TrainingDiverged
from typ.config import config_from_dict
from typ.errors import TypError
from typ.metrics import jsd_bev, mmd_bev
from typ.projection import range_to_points, to_unit
from typ.sim import simulate_scenario
from typ.voxel import Grid

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SMALL = {"range_image": {"azimuth_bins": 64, "patch": [4, 4]},
         "bev": {"grid": {"x_range": [-51.2, 51.2], "y_range": [-51.2, 51.2], "z_range": [-3.0, 7.0],
                          "shape": [32, 32, 1]}, "patch": [2, 2]},
         "unet": {"block_out_channels": [8, 16], "norm_num_groups": 8},
         "steps": 6, "checkpoint_every": 2, "batch_size": 2, "eval_samples": 3, "bootstrap": 20,
         "features": {"width": 4, "levels": 2, "steps": 2,
                      "voxel_grid": {"x_range": [-51.2, 51.2], "y_range": [-51.2, 51.2], "z_range": [-3.0, 1.0],
                                     "shape": [32, 32, 4]}}}


@pytest.fixture(scope="module")
def cfg():
    return config_from_dict({"profile": "tiny", "ddpm": SMALL}).ddpm


@pytest.fixture(scope="module")
def scans():
    out = []
    for seed in (1, 2):
        for scene in simulate_scenario(domain="target", seed=seed, n_frames=1, n_agents=2, azimuth_step_deg=2.0):
            out += [stage.Scan((scene.scenario, a, scene.timestamp), v.points, v.semantics)
                    for a, v in scene.agents.items()]
    return out


@pytest.fixture(scope="module")
def nets(cfg):
    torch.manual_seed(0)
    reps = stage.representations(cfg)
    g = cfg.features.voxel_grid
    grid = Grid(g.x_range, g.y_range, g.z_range, g.shape)
    return FeatureNets(build_net("range", cfg.features, grid), build_net("voxel", cfg.features, grid),
                       reps["range"].layout, grid)


def test_fold_is_a_lossless_reshape():
    x = torch.randn(2, 3, 8, 12)
    assert torch.equal(unfold(fold(x, 2, 4), 2, 4), x)
    assert fold(x, 2, 4).shape == (2, 24, 4, 3)
    assert torch.equal(fold(x, 2, 4)[0, :8, 0, 0], x[0, 0, :2, :4].reshape(-1))


@pytest.mark.parametrize("embedding", ["sinusoidal", "fourier"])
def test_pixel_unet_predicts_every_pixel_and_rebuilds_from_its_config(embedding):
    torch.manual_seed(0)
    model = PixelDiffusion(channels=2, height=16, width=32, patch=(2, 4), block_out_channels=(8, 16),
                           time_embedding=embedding, harmonics=3).eval()
    assert isinstance(model.unet.time_proj, FourierTimeEmbedding) == (embedding == "fourier")
    x = torch.randn(3, 2, 16, 32)
    out = model(x, torch.tensor([0, 500, 999]))
    assert out.shape == x.shape and torch.isfinite(out).all()
    again = PixelDiffusion.from_config(model.config)
    again.load_state_dict(model.state_dict())
    assert torch.equal(again.eval()(x, torch.tensor([0, 500, 999])), out)
    with pytest.raises(ValueError, match="fold"):
        PixelDiffusion(channels=1, height=18, width=32, patch=(4, 4), block_out_channels=(8, 16))


def test_paper_profile_expresses_table_one():
    c = config_from_dict({"profile": "paper"}).ddpm
    rows = {(r.name, r.representation): r for r in c.configs}
    assert {n for n, _ in rows} == {"A", "B", "C", "D", "E*", "F", "G", "H", "J"}
    expected = {"A": ("linear", "sinusoidal"), "B": ("linear", "fourier"), "C": ("hyperbolic", "fourier"),
                "D": ("hyperbolic", "sinusoidal"), "E*": ("ramp", "fourier"), "F": ("ramp", "fourier"),
                "G": ("ramp", "sinusoidal"), "H": ("time_dependent", "sinusoidal"), "J": ("time_dependent", "fourier")}
    for (name, rep), run in rows.items():
        assert (run.schedule, run.embedding) == expected[name]
    assert rows[("E*", "range")].samplers == (("ddpm", 800),) and c.samplers == (("ddpm", 1000),)
    assert c.range_image.azimuth_bins == 1024 and c.bev.grid.shape == (1024, 1024, 1) and c.seeds == (0, 1, 2)
    # E* and F train one model: the same name
    assert stage.model_name(rows[("E*", "range")], 0, "epsilon") == stage.model_name(rows[("F", "range")], 0, "epsilon")


@pytest.mark.parametrize("override,field", [
    ({"configs": [{"name": "J", "representation": "range", "schedule": "cubic", "embedding": "fourier"}]},
     "ddpm.configs[0].schedule"),
    ({"configs": [{"name": "J", "representation": "range", "schedule": "linear", "embedding": "learned"}]},
     "ddpm.configs[0].embedding"),
    ({"configs": [{"name": "J", "representation": "range", "schedule": "linear", "embedding": "fourier"},
                  {"name": "J", "representation": "range", "schedule": "ramp", "embedding": "fourier"}]},
     "ddpm.configs[1]"),
    ({"samplers": [["ddpm", 1001]]}, "ddpm.samplers[0]"),
    ({"samplers": [["heun", 10]]}, "ddpm.samplers[0][0]"),
    ({"bev": {"grid": {"shape": [128, 128, 2]}}}, "ddpm.bev.grid.shape"),
    ({"bev": {"patch": [3, 3]}}, "ddpm.bev.patch"),
    ({"eval_samples": 1}, "ddpm.eval_samples"),
    ({"unet": {"dropout": 1.5}}, "ddpm.unet.dropout"),
    ({"range_image": {"depth": "sqrt"}}, "ddpm.range_image.depth"),
    ({"prediction": "sample"}, "ddpm.prediction"),
])
def test_bad_params_name_their_field(override, field):
    with pytest.raises(TypError, match=field.replace("[", r"\[").replace("]", r"\]").replace("*", r"\*")):
        config_from_dict({"profile": "tiny", "ddpm": override})


def test_range_patch_must_fold_the_sensors_beams(cfg):
    bad = dataclasses.replace(cfg, range_image=dataclasses.replace(cfg.range_image, patch=(3, 4)))
    with pytest.raises(TypError, match="ddpm.range_image.patch"):
        stage.representations(bad)


@pytest.mark.parametrize("depth", ["linear", "log"])
def test_the_range_representation_uses_the_configured_depth_encoding(cfg, scans, depth):
    rep = stage.representations(dataclasses.replace(cfg, range_image=dataclasses.replace(cfg.range_image,
                                                                                      depth=depth)))["range"]
    img = rep.image(scans[0].points)
    px = rep.pixels(scans[0].points)
    np.testing.assert_array_equal(px, to_unit(img, rep.layout, depth=depth))
    assert rep.describe()["depth"] == depth  # part of every model's key: a change retrains
    # decoding gives back the image's points
    np.testing.assert_allclose(rep.points(px), range_to_points(img, rep.layout), rtol=2e-6, atol=1e-4)


def test_mirrored_pixels_are_the_pixels_of_the_mirrored_scan(cfg, scans):
    for rep in stage.representations(cfg).values():
        pts = scans[0].points
        flipped = pts * np.array([1, -1, 1, 1], np.float32)
        a, b = rep.mirror(rep.pixels(pts)), rep.pixels(flipped)
        assert np.mean(np.abs(a - b) > 1e-4) < 0.002, rep.name  # bins at exactly +-pi/2 may round either way


def test_metrics_equal_typ_metrics_on_the_full_sets(cfg, scans, nets):
    real = [s.points for s in scans[:2]]
    fake = [s.points[::3] + np.float32([1.0, 0.5, 0.0, 0.0]) for s in scans[2:]]
    out = score(set_stats(real, nets), [set_stats(fake, nets)], n_boot=20, seed=0)
    assert out["jsd"][0] == pytest.approx(jsd_bev(real, fake, preset="r2dm"), rel=1e-12)
    assert out["mmd"][0] == pytest.approx(mmd_bev(real, fake, preset="r2dm"), rel=1e-9, abs=1e-15)
    for m in ("jsd", "mmd", "frid", "fpvd"):
        assert out[m][1] <= out[m][2] and all(np.isfinite(out[m]))
    same = score(set_stats(real, nets), [set_stats(real, nets)], n_boot=20, seed=0)
    assert same["jsd"][0] == 0.0 and same["frid"][0] == pytest.approx(0.0, abs=1e-9)
    assert same["spread"] == pytest.approx(1.0)


def test_empty_generated_clouds_are_counted_not_fatal(scans, nets):
    real = [s.points for s in scans[:2]]
    fake = [np.zeros((0, 3), np.float32), scans[2].points]
    out = score(set_stats(real, nets), [set_stats(fake, nets)], n_boot=20, seed=0)
    assert out["empty"] == 1 and np.isfinite(out["jsd"][0]) and np.isfinite(out["mmd"][0])


def test_voxel_labels_take_the_majority_class():
    grid = Grid((0, 2), (0, 2), (0, 1), (2, 2, 1))
    pts = np.array([[0.1, 0.1, 0.5], [0.2, 0.2, 0.5], [0.3, 0.3, 0.5], [1.5, 1.5, 0.5], [1.6, 1.6, 0.5]], np.float32)
    labels = voxel_labels(pts, np.array([3, 1, 3, 2, 4], np.uint8), grid)
    assert labels.shape == (1, 2, 2)
    assert labels[0, 0, 0] == 3 and labels[0, 1, 1] == 2 and labels[0, 0, 1] == 255  # a tie goes to the lower code


def test_training_resumes_reuses_and_stops_on_nan(cfg, scans, tmp_path):
    reps = stage.representations(cfg)
    run = cfg.configs[0]
    x = stage.pixel_set(reps[run.representation], scans, mirror=True)
    data = stage.data_key(scans)
    logged = []
    first = stage.train_model(cfg, run, reps[run.representation], 0, x, data, out=tmp_path / "a",
                              log_fn=lambda v, s: logged.append(s))
    assert first.trained and logged == list(range(cfg.steps))
    again = stage.train_model(cfg, run, reps[run.representation], 0, x, data, out=tmp_path / "a", log_fn=print)
    assert not again.trained
    for k, v in first.model.state_dict().items():
        assert torch.equal(v, again.model.state_dict()[k])
    # typ.artifacts' layout: what rebuilds the model under "config", the run's fields beside it
    folder = stage.model_folder(tmp_path / "a", run, 0, cfg.prediction)
    assert folder == tmp_path / "a" / "models" / stage.network_name(run, cfg.prediction) / "seed_0"
    saved = json.loads((folder / "config.json").read_text())
    public = {k: v for k, v in first.model.config.items() if not k.startswith("_")}   # diffusers' _-keys stay out
    assert saved["config"] == json.loads(json.dumps(public)) and saved["key"] == first.key
    assert (saved["schedule"], saved["train_timesteps"]) == (run.schedule, cfg.train_timesteps)
    # a damaged or missing weights file of a model the key says to reuse names the file and the stage
    (folder / "model.safetensors").write_bytes(b"\x00" * 20)
    with pytest.raises(TypError, match=r"model.safetensors: file: expected a complete safetensors file .* ddpm stage"):
        stage.train_model(cfg, run, reps[run.representation], 0, x, data, out=tmp_path / "a", log_fn=print)
    (folder / "model.safetensors").unlink()
    with pytest.raises(TypError, match=r"model.safetensors: file: expected trained weights \(run the ddpm stage"):
        stage.train_model(cfg, run, reps[run.representation], 0, x, data, out=tmp_path / "a", log_fn=print)
    # a run killed after its step-4 checkpoint resumes there and ends with the same weights
    interrupted = dataclasses.replace(cfg, steps=4)
    stage.train_model(interrupted, run, reps[run.representation], 0, x, data, out=tmp_path / "b", log_fn=print)
    key = stage.model_key(cfg, run, reps[run.representation], 0, data)
    runs = tmp_path / "b" / "checkpoints" / stage.network_name(run, cfg.prediction) / "seed_0"   # seed_dir's layout
    (runs / stage.model_key(interrupted, run, reps[run.representation], 0, data)).rename(runs / key)
    resumed_steps = []
    resumed = stage.train_model(cfg, run, reps[run.representation], 0, x, data, out=tmp_path / "b",
                                log_fn=lambda v, s: resumed_steps.append(s))
    assert resumed_steps == [4, 5]
    for k, v in first.model.state_dict().items():
        assert torch.equal(v, resumed.model.state_dict()[k]), k
    with pytest.raises(TrainingDiverged, match="loss"):
        stage.train_model(cfg, run, reps[run.representation], 0, torch.full_like(x, float("nan")), data,
                          out=tmp_path / "c", log_fn=print)
    assert not (tmp_path / "c" / "models").exists()


def test_sampling_is_seeded_and_cached(cfg, scans, tmp_path):
    reps = stage.representations(cfg)
    run = cfg.configs[1]  # bev
    x = stage.pixel_set(reps["bev"], scans, mirror=True)
    trained = stage.train_model(cfg, run, reps["bev"], 0, x, stage.data_key(scans), out=tmp_path, log_fn=print)
    a = stage.generate(trained, "dpmsolver++", 3, 2, seed=5, out=tmp_path)
    assert a.pixels.shape == (2, 2, 32, 32) and np.abs(a.pixels).max() <= 1.0 + 1e-6  # x̂_0 clipped each step
    cached = stage.generate(trained, "dpmsolver++", 3, 2, seed=5, out=tmp_path)
    assert np.array_equal(a.pixels, cached.pixels) and cached.seconds_per_sample == a.seconds_per_sample
    for f in (tmp_path / "samples").iterdir():
        f.unlink()
    assert np.array_equal(stage.generate(trained, "dpmsolver++", 3, 2, seed=5, out=tmp_path).pixels, a.pixels)
    other = stage.generate(trained, "dpmsolver++", 3, 2, seed=6, out=tmp_path)
    assert not np.array_equal(other.pixels, a.pixels)
    assert all(len(c) >= 0 for c in stage.clouds(reps["bev"], a.pixels))


class _Oracle(torch.nn.Module):
    """The exact ``prediction`` of a data set holding one image: what a perfectly trained model returns."""

    def __init__(self, x0: torch.Tensor, abar: torch.Tensor, prediction: str):
        super().__init__()
        self.x0, self.abar, self.prediction = x0, abar, prediction
        self.config = dict(zip(("channels", "height", "width"), x0.shape[1:]))

    def forward(self, x_t, t, cond=None, adapter_features=None):
        a = self.abar[t].view(-1, 1, 1, 1)
        eps = (x_t - a.sqrt() * self.x0) / (1 - a).sqrt()
        return prediction_target(self.prediction, eps, self.x0.expand_as(x_t), self.abar[t])


def test_v_target_inverts_to_the_clean_image_and_the_noise():
    # z_t = √ᾱ x0 + √(1-ᾱ) ε and v = √ᾱ ε - √(1-ᾱ) x0 is a rotation: x0 = √ᾱ z_t - √(1-ᾱ) v,
    # ε = √(1-ᾱ) z_t + √ᾱ v (Salimans & Ho §4); at ᾱ = 1/4: v = ε/2 - √3/2 x0
    g = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(3, 2, 4, 4, generator=g), torch.randn(3, 2, 4, 4, generator=g)
    abar = torch.tensor([0.25, 0.5, 0.99])
    v = prediction_target("v_prediction", eps, x0, abar)
    torch.testing.assert_close(v[0], 0.5 * eps[0] - math.sqrt(3) / 2 * x0[0])
    a = abar.view(-1, 1, 1, 1)
    z = a.sqrt() * x0 + (1 - a).sqrt() * eps
    torch.testing.assert_close(a.sqrt() * z - (1 - a).sqrt() * v, x0)
    torch.testing.assert_close((1 - a).sqrt() * z + a.sqrt() * v, eps)
    assert prediction_target("epsilon", eps, x0, abar) is eps


@pytest.mark.parametrize("prediction", ["epsilon", "v_prediction"])
def test_generate_reads_what_the_model_predicts(prediction, tmp_path):
    # an exact model of a one-image data set samples that image back in one step, under its own
    # prediction type only (over many steps the last ones, at ᾱ near 1, would hide the mistake)
    abar = torch.from_numpy(stage.alphas_cumprod(stage.betas("linear", 100))).float()
    x0 = torch.linspace(-0.9, 0.9, 2 * 8 * 8).reshape(1, 2, 8, 8)
    oracle = _Oracle(x0, abar, prediction)
    right = stage.TrainedModel("o", prediction, oracle, "linear", 100, 0.0, False, prediction=prediction)
    wrong = dataclasses.replace(right, key="w", prediction={"epsilon": "v_prediction",
                                                            "v_prediction": "epsilon"}[prediction])
    for sampler in ("ddim", "dpmsolver++"):
        got = stage.generate(right, sampler, 1, 2, seed=0, out=tmp_path).pixels
        np.testing.assert_allclose(got, np.repeat(x0.numpy(), 2, 0), atol=1e-4)
        bad = stage.generate(wrong, sampler, 1, 2, seed=0, out=tmp_path).pixels
        assert np.abs(bad - x0.numpy()).mean() > 0.1


def test_v_prediction_trains_under_its_own_key_and_is_saved_with_it(cfg, scans, tmp_path):
    reps = stage.representations(cfg)
    run = cfg.configs[1]  # bev
    x = stage.pixel_set(reps["bev"], scans, mirror=True)
    data = stage.data_key(scans)
    vcfg = dataclasses.replace(cfg, prediction="v_prediction")
    ecfg = dataclasses.replace(cfg, prediction="epsilon")
    assert stage.model_key(vcfg, run, reps["bev"], 0, data) != stage.model_key(ecfg, run, reps["bev"], 0, data)
    v = stage.train_model(vcfg, run, reps["bev"], 0, x, data, out=tmp_path, log_fn=print)
    assert v.prediction == "v_prediction"
    folder = stage.model_folder(tmp_path, run, 0, "v_prediction")
    assert folder == tmp_path / "models" / f"{run.representation}-{run.schedule}-{run.embedding}-v" / "seed_0"
    assert stage.model_name(run, 0, "v_prediction").endswith("-v-seed0")
    assert stage.model_folder(tmp_path, run, 0, "epsilon").parent.name == folder.parent.name[:-2]
    assert json.loads((folder / "config.json").read_text())["prediction"] == "v_prediction"
    again = stage.train_model(vcfg, run, reps["bev"], 0, x, data, out=tmp_path, log_fn=print)
    assert not again.trained and again.prediction == "v_prediction"
    # the same seed and batches with the epsilon target train different weights
    e = stage.train_model(ecfg, run, reps["bev"], 0, x, data, out=tmp_path / "e", log_fn=print)
    assert e.prediction == "epsilon"
    assert any(not torch.equal(a, b) for a, b in zip(v.model.state_dict().values(), e.model.state_dict().values()))


@pytest.mark.parametrize("prediction,depth,words", [("epsilon", "linear", ("ε-prediction", "linearly")),
                                                     ("v_prediction", "log", ("v-prediction", "R2DM's log scale"))])
def test_the_report_says_what_the_model_predicts_and_how_depth_is_encoded(cfg, scans, prediction, depth, words):
    run = dataclasses.replace(cfg, prediction=prediction, range_image=dataclasses.replace(cfg.range_image, depth=depth))
    text = stage.context(run, scans, scans)["description"]
    assert all(w in text for w in words) and "{" not in text
    other = {"epsilon": "v-prediction", "v_prediction": "ε-prediction"}[prediction]
    assert other not in text


def _row(config, sampler, steps, jsd, frid, seconds, spread=0.8, rep="range", route="pixel"):
    return {"route": route, "representation": rep, "config": config, "sampler": sampler, "steps": steps,
            "seconds_per_sample": seconds, "jsd": jsd, "frid": frid, "mmd": [0, 0, 0], "fpvd": [0, 0, 0],
            "spread": spread, "schedule": "", "embedding": "", "iou": None}


def by_figure(rows):
    return {t["figure"]: t for t in targets(rows)}


def test_targets_are_judged_from_intervals():
    rows = [_row("full noise", "", 0, [0.6, 0.58, 0.62], [900, 880, 920], 0.0, route="reference"),
            _row("A", "ddpm", 1000, [0.30, 0.28, 0.32], [300, 290, 310], 6.0),
            _row("B", "ddpm", 1000, [0.29, 0.27, 0.31], [290, 280, 300], 6.0),
            _row("J", "ddpm", 1000, [0.20, 0.19, 0.21], [200, 190, 260], 6.0),
            _row("J", "dpmsolver++", 20, [0.205, 0.19, 0.22], [210, 200, 220], 0.12),
            _row("F", "ddpm", 1000, [0.25, 0.24, 0.26], [250, 240, 260], 6.0),
            _row("E*", "ddpm", 800, [0.26, 0.25, 0.27], [255, 245, 265], 4.8)]
    by = {t["figure"]: t for t in targets(rows)}
    j = by["range: J (time-dependent + Fourier) vs A/B (linear + sinusoidal/Fourier)"]
    assert j["met"] is True
    assert by["range: ramp at 800 steps (E*) vs 1000 (F)"]["met"] is True      # +4 %, 0.8x
    assert by["range J: fast solver ≤ 50 steps vs DDPM-1000"]["met"] is True    # +2.5 %, 50x
    assert by["range: samples vs noise (not flat)"]["met"] is True
    rows[3]["frid"] = [280, 250, 295]  # J's FRID interval now overlaps B's
    assert targets(rows)[0]["met"] is False
    rows[-1]["jsd"] = [0.27, 0.26, 0.28]  # +8 %
    assert {t["figure"]: t for t in targets(rows)}["range: ramp at 800 steps (E*) vs 1000 (F)"]["met"] is False
    # a respaced DDPM at <= 50 steps is a fast sampler like any other
    rows[4]["jsd"] = [0.26, 0.25, 0.27]  # J's DPM-Solver++ 20 now +30 %
    assert by_figure(rows)["range J: fast solver ≤ 50 steps vs DDPM-1000"]["met"] is False
    fifty = rows + [_row("J", "ddpm", 50, [0.204, 0.19, 0.22], [205, 195, 215], 0.3)]
    j_fast = by_figure(fifty)["range J: fast solver ≤ 50 steps vs DDPM-1000"]
    assert j_fast["met"] is True and j_fast["measured"].startswith("ddpm-50 JSD 0.204")   # +2 %, 20x
    assert by_figure(fifty)["range: J (time-dependent + Fourier) vs A/B (linear + sinusoidal/Fourier)"]["measured"] \
        == targets(rows)[0]["measured"]  # J's DDPM-1000 row is still the one compared with A and B
    only_j = [r for r in rows if r["config"] in ("J", "full noise")]
    assert {t["figure"]: t for t in targets(only_j)}[
        "range: J (time-dependent + Fourier) vs A/B (linear + sinusoidal/Fourier)"]["met"] is None
    assert not math.isnan(rows[0]["jsd"][0])


def test_random_occupancy_keeps_each_views_rate_and_is_seeded():
    truth = np.zeros((3, 8, 64, 64), bool)
    truth[0, 1] = True                      # 1/8 of the view
    truth[1, :, :32] = True                 # 1/2
    drawn = stage.random_occupancy(truth, seed=4)
    assert drawn.shape == truth.shape and drawn.dtype == bool
    np.testing.assert_allclose(drawn.reshape(3, -1).mean(1), [1 / 8, 1 / 2, 0], atol=0.01)
    assert not drawn[2].any()               # an empty view stays empty
    assert (drawn[0] != truth[0]).any()     # the rate, not the layout
    assert np.array_equal(drawn, stage.random_occupancy(truth, seed=4))
    assert not np.array_equal(drawn, stage.random_occupancy(truth, seed=5))


def test_metrics_a_row_leaves_out_are_dashes_and_nulls_not_zeros(tmp_path):
    # the latent route's rows carry FRID and spread as None (stage.BLIND_ON_VOXELS)
    blind = dict.fromkeys(stage.BLIND_ON_VOXELS)
    rows = [_row("full noise", "", 0, [0.6, 0.58, 0.62], [0.9, 0.88, 0.92], 0.0, route="reference"),
            _row("J", "ddpm", 1000, [0.20, 0.19, 0.21], [0.2, 0.19, 0.26], 6.0),
            {**_row("random occupancy", "", 0, [0.37, 0.36, 0.38], None, 0.0, rep="voxel", route="reference"), **blind},
            {**_row("TYP stage 1", "dpmsolver++", 10, [0.30, 0.29, 0.32], None, 0.2, rep="voxel", route="latent"),
             **blind, "iou": 0.33}]
    rows = [{**r, "empty": 0, "samples": [2]} for r in rows]
    context = {"description": "d", "test_scans": 4, "test_split": "test", "train_scans": 4, "train_split": "train",
               "ego_only": False, "eval_samples": 2, "bootstrap": 10, "threads": 1}
    md = ddpm_report.report(rows, round_trips={}, feature_scores={}, context=context, plot="p.png", gallery="g.png")
    head = [c.strip() for c in next(line for line in md.splitlines() if line.startswith("| row |")).split("|")]
    cells = {line.split("|")[1].strip(): dict(zip(head, (c.strip() for c in line.split("|"))))
             for line in md.splitlines() if line.startswith("| voxel ")}
    assert set(cells) == {"voxel random occupancy", "voxel TYP stage 1 dpmsolver++-10"}
    for row in cells.values():
        assert row["FRID† ↓"] == "–" and row["spread"] == "–"
    assert cells["voxel TYP stage 1 dpmsolver++-10"]["JSD ↓"] == "0.300 [0.290, 0.320]"
    assert cells["voxel TYP stage 1 dpmsolver++-10"]["IoU"] == "0.330"
    assert "Table II analogue: voxel" not in md     # the ceiling row belongs to the side by side only
    entry = ddpm_report.metrics_of(rows, {}, {}, {}, {})["rows"]["voxel TYP stage 1 dpmsolver++-10"]
    assert entry["frid"] is None and entry["spread"] is None and entry["jsd"]["value"] == 0.30
    json.dumps(entry, allow_nan=False)
    ddpm_report.pareto_plot(rows, tmp_path / "p.png")  # the FRID panel draws the pixel rows only
    assert (tmp_path / "p.png").stat().st_size > 10_000


def test_table_scores_every_row_against_the_same_held_out_scans(cfg, scans, nets, tmp_path):
    small = dataclasses.replace(cfg, samplers=(("dpmsolver++", 2),), steps=2, seeds=(0, 1),
                                configs=tuple(dataclasses.replace(r, samplers=()) for r in cfg.configs))
    reps = stage.representations(small)
    rows, trained, examples = stage.table(small, reps, scans[:3], scans[3:] + scans[:1], nets, out=tmp_path,
                                          log_fn=lambda v, s: None)
    names = [(r["representation"], r["config"], r["sampler"]) for r in rows]
    assert names == [("range", "full noise", ""), ("range", "real train views", ""),
                     ("bev", "full noise", ""), ("bev", "real train views", ""),
                     ("range", "J", "dpmsolver++"), ("bev", "J", "dpmsolver++")]
    assert set(trained) == {f"{r}-time_dependent-fourier-v-seed{s}" for r in ("range", "bev") for s in (0, 1)}
    for r in rows:
        # reference rows are sized like model rows: 2 noise sets (2 seeds), and as many disjoint sets of
        # 3 training scans as the 3 scans allow
        assert r["samples"] == ([3, 3] if r["route"] == "pixel" or r["config"] == "full noise" else [3])
        assert all(r[m][1] <= r[m][2] for m in ("jsd", "mmd", "frid", "fpvd"))
    # the train scans are closer to the held-out ones than pure noise is
    by = {(r["representation"], r["config"]): r for r in rows}
    for rep in ("range", "bev"):
        assert by[(rep, "real train views")]["jsd"][0] < by[(rep, "full noise")]["jsd"][0]
    assert {"range real", "bev real", "range J dpmsolver++-2", "bev J dpmsolver++-2"} == set(examples)


def test_reference_sets_are_sized_like_a_model_row(cfg):
    two = dataclasses.replace(cfg, eval_samples=4, seeds=(0, 1, 2),
                              configs=tuple(dataclasses.replace(r, seeds=()) for r in cfg.configs))
    rep = stage.representations(two)["range"]
    own = np.arange(10, dtype=np.float32)[:, None, None, None] * np.ones((1, *rep.shape), np.float32)
    noise, real = stage.reference_sets(two, rep, own)
    # 3 seeds -> 3 noise sets of 4, each its own draw; 10 images hold only 2 whole disjoint sets of 4
    assert [x.shape for x in noise] == [(4, *rep.shape)] * 3
    assert not np.array_equal(noise[0], noise[1])
    np.testing.assert_array_equal(noise[0], stage.full_noise(rep, 4, two.seed))
    assert [len(x) for x in real] == [4, 4]
    ids = [set(x[:, 0, 0, 0].astype(int).tolist()) for x in real]
    assert len(ids[0] | ids[1]) == 8  # disjoint
    again = stage.reference_sets(two, rep, own)[1]
    assert all(np.array_equal(a, b) for a, b in zip(real, again))
    # fewer images than one set: one set of all of them
    assert [len(x) for x in stage.reference_sets(two, rep, own[:3])[1]] == [3]


def test_the_bench_sweep_is_a_valid_config_covering_table_one():
    from pathlib import Path

    from bench_modules import ROOT as repo, load_bench

    bench = load_bench("ddpm")
    sweep_params = bench.sweep_params

    for mode in ({}, {"quick": True}, {"medium": True}):
        params = sweep_params(repo, **mode)
        cfg = config_from_dict(params).ddpm
        assert Path(cfg.latent.stage1).is_absolute() and Path(cfg.latent.stage1).name == "stage1"
    medium = config_from_dict(sweep_params(repo, medium=True))
    assert {(r.name, r.schedule, r.embedding, len(r.seeds)) for r in medium.ddpm.configs} == {
        ("J", "time_dependent", "fourier", 3), ("A", "linear", "sinusoidal", 3), ("B", "linear", "fourier", 1),
        ("E*", "ramp", "fourier", 1), ("F", "ramp", "fourier", 1)}
    # E* and F are one trained model sampled with 800 and 1000 DDPM steps
    rows = {(r.name, s, n) for r, s, n in stage.sample_rows(medium.ddpm)}
    assert {("E*", "ddpm", 800), ("F", "ddpm", 1000), ("J", "ddpm", 1000), ("A", "dpmsolver++", 20)} <= rows
    assert medium.simulate == config_from_dict({"profile": "tiny"}).simulate  # the tiny pipeline's data
    # --depth overrides the range image's encoding and nothing else of it
    assert medium.ddpm.range_image == config_from_dict({"profile": "tiny"}).ddpm.range_image
    linear = config_from_dict(sweep_params(repo, medium=True, depth="linear")).ddpm
    assert linear.range_image == dataclasses.replace(medium.ddpm.range_image, depth="linear")
    # --prediction overrides what the U-Net outputs and nothing else
    eps = config_from_dict(sweep_params(repo, medium=True, prediction="epsilon")).ddpm
    assert medium.ddpm.prediction == "v_prediction" and eps == dataclasses.replace(medium.ddpm, prediction="epsilon")
    assert [bench.bench_stem(*a) for a in ((None, None), ("linear", None), ("linear", "epsilon"), (None, "v_prediction"))] \
        == ["bench_ddpm", "bench_ddpm_linear", "bench_ddpm_linear_epsilon", "bench_ddpm_v"]
    full = config_from_dict(sweep_params(repo, quick=False)).ddpm
    seeds = {r.name: len(r.seeds) for r in full.configs}
    assert seeds == {"A": 3, "B": 3, "C": 1, "D": 1, "E*": 3, "F": 3, "G": 1, "H": 1, "J": 3}
    rows = {(r.name, s, n) for r, s, n in stage.sample_rows(full)}
    assert ("E*", "ddpm", 800) in rows and ("F", "ddpm", 1000) in rows and ("J", "dpmsolver++", 20) in rows
    # E* is F sampled with fewer steps: one set of trained models
    by = {r.name: r for r in full.configs}
    assert stage.model_name(by["E*"], 1, "epsilon") == stage.model_name(by["F"], 1, "epsilon")
