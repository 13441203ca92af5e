"""Stage-1 network and post-processing: shapes, conditioning, adapter residuals, thresholds."""
import numpy as np
import pytest
import torch
from diffusers import T2IAdapter
from diffusers.models.attention_processor import Attention, AttnProcessor2_0

from models.ldm import LatentDiffusion, OneTokenAttnProcessor
from models.postprocess import postprocess
from models.time_embedding import FourierTimeEmbedding


def _ldm(**kw):
    torch.manual_seed(0)
    return LatentDiffusion(latent_channels=8, cond_channels=3, sample_size=16, block_out_channels=(16, 16, 16, 16),
                           cross_attention_dim=8, attention_head_dim=4, norm_num_groups=4, **kw)


def test_eps_shape_and_condition_matters():
    m = _ldm().eval()
    z = torch.randn(2, 8, 16, 16)
    t = torch.tensor([10, 900])
    c1, c2 = torch.randn(2, 3, 16, 16), torch.randn(2, 3, 16, 16)
    with torch.no_grad():
        e1, e2 = m(z, t, c1), m(z, t, c2)
    assert e1.shape == (2, 8, 16, 16)
    assert not torch.allclose(e1, e2)


def test_fourier_time_embedding_is_used():
    m = _ldm(time_embedding="fourier")
    assert isinstance(m.unet.time_proj, FourierTimeEmbedding)
    with torch.no_grad():
        out = m(torch.randn(1, 8, 16, 16), torch.tensor([5]), torch.randn(1, 3, 16, 16))
    assert torch.isfinite(out).all()


def test_t2i_adapter_residuals_fit_the_encoder():
    """DESIGN: a full_adapter with downscale_factor=1 on x^f yields one residual per UNet level."""
    m = _ldm().eval()
    adapter = T2IAdapter(in_channels=8, channels=[16, 16, 16, 16], num_res_blocks=1, downscale_factor=1,
                         adapter_type="full_adapter")
    feats = adapter(torch.randn(2, 8, 16, 16))
    assert [f.shape[-1] for f in feats] == [16, 8, 4, 2]
    z, t, c = torch.randn(2, 8, 16, 16), torch.tensor([3, 3]), torch.randn(2, 3, 16, 16)
    with torch.no_grad():
        plain = m(z, t, c)
        zero = m(z, t, c, [torch.zeros_like(f) for f in feats])
        with_adapter = m(z, t, c, list(feats))
    assert torch.allclose(plain, zero, atol=1e-5)
    assert not torch.allclose(plain, with_adapter)


def test_statistics_round_trip():
    m = _ldm()
    lat, cond = torch.randn(20, 8, 16, 16) * 3 + 1, torch.randn(20, 3, 16, 16) * 0.1
    m.set_statistics(lat, cond)
    z = m.normalize(lat)
    assert torch.allclose(z.mean((0, 2, 3)), torch.zeros(8), atol=1e-5)
    assert torch.allclose(z.std((0, 2, 3)), torch.ones(8), atol=1e-4)
    assert torch.allclose(m.denormalize(z), lat, atol=1e-5)
    restored = LatentDiffusion.from_config(m.config)
    restored.load_state_dict(m.state_dict())
    assert torch.equal(restored.latent_std, m.latent_std)


def test_postprocess_thresholds():
    logits = torch.logit(torch.tensor([0.05, 0.2, 0.5, 0.8, 0.95]))
    hard = postprocess(logits, low=0.5, high=0.5, noise_std=0.0)
    assert hard.tolist() == [False, False, False, True, True]
    # below low always dropped, above high always kept, whatever the noise
    for seed in range(5):
        out = postprocess(logits, low=0.1, high=0.9, noise_std=10.0, generator=torch.Generator().manual_seed(seed))
        assert not out[0] and out[4]
    # in between: the fraction kept follows P(logit + noise > 0)
    mid = torch.full((20000,), torch.logit(torch.tensor(0.5)).item())
    frac = postprocess(mid, low=0.1, high=0.9, noise_std=1.0, generator=torch.Generator().manual_seed(0)).float().mean()
    assert abs(frac.item() - 0.5) < 0.02
    with pytest.raises(ValueError):
        postprocess(logits, low=0.8, high=0.2, noise_std=1.0)


def test_tune_thresholds_finds_the_best_pair():
    from tasks.stage1 import tune_thresholds
    from typ.config import config_from_dict

    cfg = config_from_dict({"stage1": {"postprocess": {"noise_std": 0.0, "candidates": [0.2, 0.5, 0.8]}}}).stage1
    truth = torch.tensor([[1.0, 1.0, 0.0, 0.0]])
    logits = torch.logit(torch.tensor([[0.6, 0.3, 0.1, 0.25]]))
    best = tune_thresholds(logits, truth, cfg, seed=0)
    # threshold 0.2 keeps {0.6, 0.3, 0.25} (IoU 2/3); 0.5 keeps {0.6} (IoU 1/2): 0.2 wins
    assert (best["low"], best["high"]) == (0.2, 0.2) and best["iou"] == pytest.approx(2 / 3)
    assert np.isfinite(best["iou"])


@pytest.mark.parametrize("self_attention", [False, True])
def test_one_token_attention_is_diffusers_attention(self_attention):
    """The short-cut processor gives diffusers' own attention's output and gradients: attention to
    the one context token is to_out(to_v(context)) in every cell. With self_attention the
    self-attention layers fall back to diffusers' processor."""
    fast = _ldm(self_attention=self_attention)
    assert {type(p) for p in fast.unet.attn_processors.values()} == {OneTokenAttnProcessor}
    plain = _ldm(self_attention=self_attention)
    plain.unet.set_attn_processor(AttnProcessor2_0())
    assert all(torch.equal(a, b) for a, b in zip(fast.state_dict().values(), plain.state_dict().values()))
    torch.manual_seed(1)
    z, t, c = torch.randn(2, 8, 16, 16), torch.tensor([40, 700]), torch.randn(2, 3, 16, 16)
    grads = []
    for m in (fast, plain):
        out = m(z, t, c)
        (out ** 2).mean().backward()
        grads.append({n: p.grad for n, p in m.named_parameters()})
        grads[-1]["out"] = out.detach()
    assert torch.allclose(grads[0]["out"], grads[1]["out"], rtol=1e-5, atol=1e-6)
    assert not torch.allclose(grads[0]["out"], torch.zeros_like(grads[0]["out"]))
    skipped = []
    for name, g in grads[1].items():
        mine = grads[0][name]
        if mine is None:     # to_q, to_k and the norm before them: softmax over one key is 1 whatever they give
            assert torch.count_nonzero(g) == 0, name
            skipped.append(name)
        else:
            assert torch.allclose(mine, g, rtol=1e-4, atol=1e-7), name
    assert skipped and all(".to_q." in n or ".to_k." in n or ".norm" in n for n in skipped)
    assert not any(".attn1.to_q." in n for n in skipped) if self_attention else True


@pytest.mark.parametrize("batch, queries, tokens", [(1, 3, 3), (2, 5, 3), (2, 4, 2)])
def test_one_token_attention_fed_several_tokens_computes_the_attention(batch, queries, tokens):
    """Several context tokens: softmax over them is not 1 per token, so the short-cut does not hold
    and the processor must give diffusers' attention, written out here as
    to_out(softmax(q k^T / sqrt(d)) v) per head. (1, 3, 3): as many queries as tokens, where a
    short-cut taken would broadcast without an error; a batch of 1 tells the token axis from the
    batch axis. With one token it is to_out(to_v(context)) in every query."""
    torch.manual_seed(0)
    attn = Attention(query_dim=8, cross_attention_dim=6, heads=2, dim_head=4).eval()
    x, context = torch.randn(batch, queries, 8), torch.randn(batch, tokens, 6)

    def exact(context: torch.Tensor) -> torch.Tensor:
        def heads(t: torch.Tensor) -> torch.Tensor:   # (B, N, 8) -> (B, 2, N, 4)
            return t.reshape(t.shape[0], t.shape[1], 2, 4).transpose(1, 2)

        q, k, v = heads(attn.to_q(x)), heads(attn.to_k(context)), heads(attn.to_v(context))
        w = torch.softmax(q @ k.transpose(-1, -2) / 4 ** 0.5, dim=-1)
        return attn.to_out[0]((w @ v).transpose(1, 2).reshape(batch, queries, 8))

    with torch.no_grad():
        got = OneTokenAttnProcessor()(attn, x, context)
        torch.testing.assert_close(got, exact(context), rtol=1e-5, atol=1e-6)
        assert not torch.allclose(got, got[:, :1].expand_as(got), atol=1e-4)   # the queries do matter
        one = OneTokenAttnProcessor()(attn, x, context[:, :1])
        torch.testing.assert_close(one, exact(context[:, :1]), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(one, attn.to_out[0](attn.to_v(context[:, :1])).expand_as(one))
