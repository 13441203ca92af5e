"""The stage-1 UNet's attention to its one context token: diffusers' processor against typ's short-cut.

    python bench/attention.py [--out reports] [--rounds 5] [--steps 6]

The tiny profile's stage-1 network (``tasks.stage1.build`` on the profile's ``stage1.unet``; latents
8 x 32 x 32 and a 1 x 32 x 32 box map, the tiny run's shapes; batch 8), built twice from one
seed: once with ``models.ldm.OneTokenAttnProcessor`` (what typ runs) and once with diffusers'
``AttnProcessor2_0`` on every attention layer (what it ran before). Measured side by side in one
process on the same inputs, the two taking turns for ``--rounds`` rounds:

- training step: forward, the z_0 MSE, backward and an AdamW step (``--steps`` per round);
- sampling forward: one no-grad forward, what each of a sampler's steps costs (``--steps`` per round).

Times are medians over rounds of the per-step mean. Outputs are compared on the first batch:
the forward of the two must agree (bit for bit on the machines measured so far), and after the
timed training steps the weights may differ by float rounding of the gradients only.
Writes ``<out>/bench_attention.md`` atomically and prints it.
"""
from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

from diffusers.models.attention_processor import AttnProcessor2_0  # noqa: E402

from tasks.stage1 import build  # noqa: E402
from typ.config import config_from_dict  # noqa: E402
from typ.io import write_text  # noqa: E402

LATENT, COND, SIZE, BATCH = 8, 1, 32, 8   # the tiny run's stage-1 inputs
FAST, BASELINE = "typ (one-token short-cut)", "diffusers AttnProcessor2_0"


def networks(profile: str) -> dict[str, torch.nn.Module]:
    cfg = config_from_dict({"profile": profile}, where=f"profile {profile}").stage1
    torch.manual_seed(0)
    fast = build(cfg, LATENT, COND, SIZE)
    plain = build(cfg, LATENT, COND, SIZE)
    plain.load_state_dict(fast.state_dict())
    plain.unet.set_attn_processor(AttnProcessor2_0())
    return {FAST: fast, BASELINE: plain}


def run(profile: str = "tiny", rounds: int = 5, steps: int = 6) -> dict:
    """Median seconds per training step and per sampling forward of each processor, the forward
    outputs' max |difference| and the weights' after the timed training (module doc)."""
    nets = networks(profile)
    g = torch.Generator().manual_seed(1)
    z = torch.randn(BATCH, LATENT, SIZE, SIZE, generator=g)
    c = torch.randn(BATCH, COND, SIZE, SIZE, generator=g)
    t = torch.randint(0, 1000, (BATCH,), generator=g)
    with torch.no_grad():
        outs = [m(z, t, c) for m in nets.values()]
    opts = {name: torch.optim.AdamW(m.parameters(), lr=1e-3) for name, m in nets.items()}

    def train_step(name: str) -> None:
        m = nets[name].train()
        loss = (m(z, t, c) - z).pow(2).mean()
        opts[name].zero_grad(set_to_none=True)
        loss.backward()
        opts[name].step()

    def sample_step(name: str) -> None:
        with torch.no_grad():
            nets[name].eval()(z, t, c)

    for name in nets:                      # warm-up: allocator, oneDNN primitives
        train_step(name)
        sample_step(name)
    times = {(name, kind): [] for name in nets for kind in ("train", "sample")}
    for _ in range(rounds):
        for name in nets:
            for kind, fn in (("train", train_step), ("sample", sample_step)):
                t0 = time.perf_counter()
                for _ in range(steps):
                    fn(name)
                times[name, kind].append((time.perf_counter() - t0) / steps)
    fast, plain = nets.values()
    return {"profile": profile, "rounds": rounds, "steps": steps,
            "seconds": {name: {kind: statistics.median(times[name, kind]) for kind in ("train", "sample")}
                        for name in nets},
            "forward_diff": float((outs[0] - outs[1]).abs().max()),
            "weights_diff": max(float((a - b).abs().max()) for a, b in zip(fast.state_dict().values(),
                                                                             plain.state_dict().values()))}


def table(result: dict) -> str:
    """The page of :func:`run`'s result."""
    sec = result["seconds"]
    base = sec[BASELINE]
    rows = [f"| {name} | {s['train']:.3f} | {base['train'] / s['train']:.2f}x | {s['sample']:.3f} "
            f"| {base['sample'] / s['sample']:.2f}x |" for name, s in sec.items()]
    diff = result["forward_diff"]
    return "\n".join([
        "# Stage-1 attention to the one context token",
        "",
        f"The {result['profile']} profile's stage-1 UNet, latents {LATENT} x {SIZE} x {SIZE} with a {COND} x {SIZE} x "
        f"{SIZE} box map, batch {BATCH}; {result['rounds']} rounds of {result['steps']} steps, the two processors "
        f"taking turns in one process; {torch.get_num_threads()} torch threads, "
        f"{platform.processor() or platform.machine()}. Method: `bench/attention.py`.",
        "",
        "| processor | s / training step | speed-up | s / sampling forward | speed-up |",
        "|---|---|---|---|---|",
        *rows,
        "",
        f"- Forward outputs before training: max |difference| {diff:.1e} "
        f"({'bit-identical' if diff == 0 else 'not bit-identical'}).",
        f"- Weights after {1 + result['rounds'] * result['steps']} training steps each: max |difference| "
        f"{result['weights_diff']:.1e} (the gradients of to_out and to_v are summed over the cells in another "
        "order).",
        "",
    ])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="reports", type=Path)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--profile", default="tiny")
    args = parser.parse_args()
    text = table(run(args.profile, args.rounds, args.steps))
    write_text(args.out / "bench_attention.md", text)
    print(text)


if __name__ == "__main__":
    main()
