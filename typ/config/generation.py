"""The blocks of TYP's generator: ``vqvae``, ``stage1``, ``adapt``, ``stage2``, ``selftrain`` and
``generate`` (TYP §3)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Annotated, Literal

from typ.config.base import (LEVELS, MAX_ADAPTER_SCALE, MAX_NOISE_STD, BatchSize, Bound, Decay, Distance, Epochs,
                             LayersPerBlock, LearningRate, Length, NormGroups, Probability, Sampler, Schedule, Seed,
                             Steps, Timesteps, Views, Width, Workers)
from typ.errors import TypError
from typ.registry import COMPOSE_MODES

FocalGamma = Annotated[float, Bound(0, 10, "a focal-loss exponent: TYP's is 2 (0: plain BCE)")]
AdapterScale = Annotated[float, Bound(0, MAX_ADAPTER_SCALE, "a multiplier of the adapter's residuals: past it "
                                      "they drown the UNet", low_open=True)]


@dataclass(frozen=True)
class AutoencoderConfig:
    """One VQ-VAE of TYP §3.2 (x or y): widths per level (``len - 1`` halvings), code size."""

    block_out_channels: Annotated[tuple[Width, ...], LEVELS]
    latent_channels: Annotated[int, Bound(1, 256, "channels of a latent cell: the paper's x^f has 8")]
    num_codes: Annotated[int, Bound(1, 65_536, "codebook entries, each compared with every latent cell: the "
                                    "paper's 1024")]
    norm_num_groups: NormGroups
    gamma: FocalGamma
    epochs: Epochs
    #: "ema": EMA codebook with k-means init and dead-code restarts; "vq": Eq. 1's codebook term
    quantizer: Literal["ema", "vq"] = "ema"
    #: y only: "vqvae" (TYP: E_y, Q_y, G_y) or "pool" (the box map averaged per latent cell)
    encoding: Literal["vqvae", "pool"] = "vqvae"
    ema_decay: Annotated[float, Bound(0, 1, "an EMA decay", low_open=True, high_open=True)] = 0.9
    dead_code_threshold: Annotated[float, Bound(0, 1e6, "an EMA cluster size: a code used less is restarted")] = 1.0

    def check(self, where: str, name: str) -> None:
        if any(c % self.norm_num_groups for c in self.block_out_channels):
            raise TypError(where, f"{name}.block_out_channels",
                           f"positive widths divisible by norm_num_groups={self.norm_num_groups}",
                           list(self.block_out_channels))


@dataclass(frozen=True)
class VQVAEStageConfig:
    """Stage ``vqvae``: E_x,Q_x,G_x and E_y,Q_y,G_y trained on the target domain's ego views."""

    x: AutoencoderConfig
    y: AutoencoderConfig
    batch_size: BatchSize
    lr: LearningRate
    seed: Seed
    checkpoint_every: Steps
    threshold: Probability
    input: str
    dataset: str
    train_split: str
    eval_split: str
    out: str

    def check(self, where: str, name: str) -> None:
        self.x.check(where, f"{name}.x")
        self.y.check(where, f"{name}.y")
        if len(self.x.block_out_channels) != len(self.y.block_out_channels):
            raise TypError(where, f"{name}.y.block_out_channels",
                           "as many levels as x (x^f and y^f must share one latent resolution)",
                           list(self.y.block_out_channels))


@dataclass(frozen=True)
class UNetConfig:
    """ε_θ's UNet: widths per level (latents are halved ``len - 1`` times), time embedding."""

    block_out_channels: Annotated[tuple[Width, ...], LEVELS]
    layers_per_block: LayersPerBlock
    cross_attention_dim: Width
    attention_head_dim: Width
    norm_num_groups: NormGroups
    time_embedding: Literal["sinusoidal", "fourier"]
    #: the transformer blocks' self-attention over latent cells (off: cross-attention only, 2x faster)
    self_attention: bool = True
    #: x, y, range channels as input (the scan pattern depends on where a cell is)
    coordinates: bool = False

    def check(self, where: str, name: str) -> None:
        if len(self.block_out_channels) < 2 or any(c % self.norm_num_groups for c in self.block_out_channels):
            raise TypError(where, f"{name}.block_out_channels",
                           f">= 2 positive widths divisible by norm_num_groups={self.norm_num_groups}",
                           list(self.block_out_channels))


@dataclass(frozen=True)
class PostprocessConfig:
    """TYP §4.1: thresholds low/high chosen from ``candidates`` on the validation split."""

    noise_std: Annotated[float, Bound(0, MAX_NOISE_STD, "a standard deviation of logit noise: TYP's is 1")]
    candidates: Annotated[tuple[Probability, ...], Length(1, 32, "thresholds, every pair of them scored on the "
                                                          "validation split")]


@dataclass(frozen=True)
class Stage1Config:
    """Stage ``stage1`` (TYP Eq. 4): P(x|y) as a latent diffusion model on the target's ego views."""

    unet: UNetConfig
    schedule: Schedule
    train_timesteps: Timesteps
    epochs: Epochs
    batch_size: BatchSize
    lr: LearningRate
    seed: Seed
    checkpoint_every: Steps
    sampler: Sampler
    sample_steps: Timesteps
    eta: Annotated[float, Bound(0, 1, "DDIM's eta: 0 is deterministic, 1 is DDPM's variance")]
    postprocess: PostprocessConfig
    eval_views: Views
    input: str
    vqvae: str
    dataset: str
    train_split: str
    val_split: str
    out: str
    #: weights averaged with this decay sample the model (the training weights do not)
    ema_decay: Decay = 0.999
    warmup_steps: Steps = 100
    lr_schedule: Literal["constant", "cosine"] = "cosine"
    #: models trained with seeds seed, seed + 1, ... (the first feeds later stages)
    replicas: Annotated[int, Bound(1, 32, "trainings of the generator, one per seed: the paper's tables use 3")] = 1
    #: what the UNet outputs (Eq. 4's minimiser either way): epsilon, sample (z_0) or v_prediction
    prediction: Literal["epsilon", "sample", "v_prediction"] = "epsilon"
    #: Min-SNR-γ loss weighting (0: the plain mean squared error of Eq. 4)
    min_snr: Annotated[float, Bound(0, 1000, "Min-SNR's gamma: 5 in its paper")] = 0.0
    #: train on the ego views of the training split only (True), or on every agent's view, each
    #: taken alone as one more single-agent scan of the target domain (no pairing is used)
    ego_only: bool = True

    def check(self, where: str, name: str) -> None:
        self.unet.check(where, f"{name}.unet")
        if not 1 <= self.sample_steps <= self.train_timesteps:
            raise TypError(where, f"{name}.sample_steps", f"an integer in [1, train_timesteps={self.train_timesteps}]",
                           self.sample_steps)
        if self.eta and self.sampler != "ddim":
            raise TypError(where, f"{name}.eta", "0, or >= 0 with sampler ddim", self.eta)


@dataclass(frozen=True)
class AdaptConfig:
    """Stage ``adapt`` (TYP Eq. 8–10): E_src, G_src against a hinge discriminator on x^f."""

    disc_width: Width
    epochs: Epochs
    batch_size: BatchSize
    lr: LearningRate
    lr_disc: LearningRate
    gamma: FocalGamma
    seed: Seed
    checkpoint_every: Steps
    #: the hinge loss is 2 at chance; far past it training has diverged
    max_disc_loss: Annotated[float, Bound(0, 1e6, "a hinge loss, 2 at chance", low_open=True)]
    eval_views: Views
    input: str
    vqvae: str
    source_dataset: str
    source_split: str
    target_dataset: str
    target_split: str
    out: str

    def check(self, where: str, name: str) -> None:
        pass  # the bounds beside the fields are the whole check


@dataclass(frozen=True)
class Stage2Config:
    """Stage ``stage2`` (TYP Eq. 5–7): a T2I-Adapter on x^f_e' trained on source tuples, UNet frozen.

    One adapter per stage-1 replica. ``resim`` also trains the re-simulation-conditioned
    adapter (x^f_e' beside the re-simulated view's latent); ``one_stage`` also trains TYP
    Table 5's one-stage model (UNet and adapter together from scratch on the source tuples,
    for as many steps as stage 1 and stage 2 together); ``augment``: 1, 2 (mirror) or 8
    (rotations and mirrors) symmetries per tuple; ``max_pairs``: source tuples used (0: all).
    """

    adapter_res_blocks: LayersPerBlock
    epochs: Epochs
    batch_size: BatchSize
    lr: LearningRate
    seed: Seed
    checkpoint_every: Steps
    sim: str
    voxels: str
    vqvae: str
    adapt: str
    stage1: str
    source_domain: str
    source_split: str
    out: str
    warmup_steps: Steps = 100
    lr_schedule: Literal["constant", "cosine"] = "cosine"
    ema_decay: Decay = 0.999
    augment: Literal[1, 2, 8] = 2
    max_pairs: Annotated[int, Bound(0, 100_000_000, "source tuples used, a cap (0: all)")] = 0
    resim: bool = False
    one_stage: bool = False

    def check(self, where: str, name: str) -> None:
        pass  # the bounds beside the fields are the whole check


@dataclass(frozen=True)
class SelftrainConfig:
    """Stage ``selftrain`` (TYP §3.4): fine-tune the adapter on source tuples plus target data.

    Switches (TYP Table 4): ``discriminator`` — source tuples encoded by the adapted E_src
    (stage ``adapt``; off: by E_tgt, the adapter trained anew: "no adaptation");
    ``self_training`` — pseudo references (x̂_r, x_e', y_r) sampled in target scenes;
    ``dummy_ego`` — target ego views (x_r, y_r) with an empty ego, x_e = 0. ``ablation``
    also trains every row of Table 4, whatever the switches say. ``generator``: which adapter
    the written generator (``<out>/generator``) carries: ``typ`` (the switches' variant) or
    ``typ_resim`` (the same recipe on the re-simulation-conditioned adapter; needs
    ``stage2.resim``). The generator samples with ``sampler`` / ``sample_steps`` and multiplies the
    adapter's residuals by ``adapter_scale`` (diffusers' ``adapter_conditioning_scale``; 1: as trained).
    """

    discriminator: bool
    self_training: bool
    dummy_ego: bool
    ablation: bool
    pseudo_references: Annotated[int, Bound(1, 100_000, "pseudo references, each a diffusion sample: the paper's "
                                            "2000")]
    min_distance: Distance
    max_distance: Annotated[float, Bound(0, 1000, "metres: 1 km is past every LiDAR's range", low_open=True)]
    epochs: Epochs
    batch_size: BatchSize
    lr: LearningRate
    seed: Seed
    checkpoint_every: Steps
    sampler: Sampler
    sample_steps: Timesteps
    sim: str
    voxels: str
    vqvae: str
    adapt: str
    stage1: str
    stage2: str
    source_domain: str
    source_split: str
    target_domain: str
    target_split: str
    out: str
    warmup_steps: Steps = 50
    lr_schedule: Literal["constant", "cosine"] = "cosine"
    ema_decay: Decay = 0.999
    generator: Literal["typ", "typ_resim"] = "typ"
    adapter_scale: AdapterScale = 1.0

    def check(self, where: str, name: str) -> None:
        if not self.min_distance < self.max_distance:
            raise TypError(where, f"{name}.min_distance", f"0 <= min_distance < max_distance={self.max_distance}",
                           self.min_distance)


@dataclass(frozen=True)
class GenerateSet:
    """One (dataset, split) of single-agent scenarios to turn collaborative.

    references: ``vehicles`` — reference poses sampled from the ego's labelled vehicles
    (TYP §4.5, the ColWaymo analogue); ``cavs`` — the scenario's own cooperating agents, each
    replaced by a cloud generated from the ego's at its true pose (only their poses are read:
    the oracle comparison of TYP Tables 1–2).
    """

    dataset: str
    split: str
    references: Literal["vehicles", "cavs"]


@dataclass(frozen=True)
class CastConfig:
    """The scene a cast reference view is cast from (``generate.compose: cast``, :mod:`typ.castview`);
    ``reports/generation_ablation.md`` measures each choice."""

    #: labelled vehicles (y_r) as closed boxes, each edge scaled by this; 0: none
    label_boxes: Annotated[float, Bound(0, 2, "a scale of each box edge (0: no label boxes)")] = 0.9
    #: the road surface lies under ``generated`` ground voxels only, every cell the ego did not
    #: see (``unseen``) or ``everywhere`` (under the ego's surfels too)
    road: Literal["generated", "unseen", "everywhere"] = "unseen"
    #: drop generated voxels an ego ray crossed before its return: the ego saw them empty
    carve: bool = True


#: ``generate.compose``: what a reference view is made of (:class:`GenerateConfig`), the registry's names
COMPOSE = tuple(COMPOSE_MODES)


@dataclass(frozen=True)
class GenerateConfig:
    """Stage ``generate`` (TYP §4.5): reference views for single-agent frames, written as OPV2V agents."""

    references_per_frame: Annotated[int, Bound(1, 64, "reference views per frame, each a diffusion sample of "
                                               "seconds: TYP's 2; OPV2V scenes hold at most 7 cars")]
    #: roadside units per scenario (``vehicles`` sets): virtual sensors on observed ground, facing the ego
    roadside_units: Annotated[int, Bound(0, 64, "roadside views per scenario, each a diffusion sample")]
    min_distance: Distance
    max_distance: Annotated[float, Bound(0, 1000, "metres: 1 km is past every LiDAR's range", low_open=True)]
    sampler: Sampler
    sample_steps: Timesteps
    seed: Seed
    input: str
    sets: Annotated[tuple[GenerateSet, ...], Length(1, 64, "{dataset, split, references} sets, each "
                                                                   "generated whole")]
    #: the folder selftrain writes the trained generators to (``<generator>/generator/seed_<s>``)
    generator: str
    out: str
    workers: Workers
    #: what a reference view is made of: ``generated`` — the generator's sample alone (TYP);
    #: ``hybrid`` — the ego's cloud re-simulated from the reference pose in the BEV cells the ego
    #: saw, the generator's sample elsewhere (the ``hybrid`` row of reports/generation_accuracy.md);
    #: ``cast`` — one scene of both (the ego's surfels, the generated cells), cast once with the
    #: reference LiDAR (:mod:`typ.castview`, shaped by ``cast``)
    compose: Literal[COMPOSE] = "generated"
    cast: CastConfig = dataclasses.field(default_factory=CastConfig)

    def check(self, where: str, name: str) -> None:
        if not self.min_distance < self.max_distance:
            raise TypError(where, f"{name}.min_distance", f"0 <= min_distance < max_distance={self.max_distance}",
                           self.min_distance)
        seen = set()
        for i, s in enumerate(self.sets):
            if (s.dataset, s.split) in seen:
                raise TypError(where, f"{name}.sets[{i}]", "each (dataset, split) once", [s.dataset, s.split])
            seen.add((s.dataset, s.split))
