"""VQ-VAE (Eq. 1): shapes, straight-through gradients, codebook terms, and that it learns."""
import torch

from models.vqvae import BEVVQVAE


def _model(**kw):
    torch.manual_seed(0)
    return BEVVQVAE(in_channels=4, latent_channels=3, block_out_channels=(8, 16, 16), num_codes=16,
                    norm_num_groups=4, **kw)


def test_shapes_and_downsampling():
    m = _model()
    x = (torch.rand(2, 4, 32, 32) < 0.1).float()
    out = m(x)
    assert m.downsample == 4
    assert out.latents.shape == (2, 3, 8, 8) and out.quantized.shape == (2, 3, 8, 8)
    assert out.logits.shape == (2, 4, 32, 32)
    assert out.indices.shape == (2, 8, 8) and out.indices.max() < 16


def test_codebook_loss_is_eq1_with_equal_weights():
    m = _model()
    x = (torch.rand(2, 4, 32, 32) < 0.1).float()
    out = m(x)
    codes = m.net.quantize.embedding.weight[out.indices]          # (B, h, w, c)
    z = out.latents.permute(0, 2, 3, 1)
    expected = 2 * ((codes - z) ** 2).mean()                        # both terms, weight 1
    assert torch.allclose(out.codebook_loss, expected, rtol=1e-5)
    # the quantized value equals the chosen code (forward), gradient flows to the encoder
    assert torch.allclose(out.quantized.permute(0, 2, 3, 1), codes, atol=1e-6)


def test_straight_through_gradient_reaches_encoder_and_codebook():
    m = _model()
    x = (torch.rand(2, 4, 32, 32) < 0.1).float()
    loss, _, parts = m.loss(x, gamma=2.0)
    loss.backward()
    enc = m.net.encoder.conv_in.weight.grad
    assert enc is not None and enc.abs().sum() > 0
    assert m.net.quantize.embedding.weight.grad.abs().sum() > 0
    assert set(parts) == {"loss", "rec", "codebook"}


def test_overfits_one_batch():
    m = _model()
    g = torch.Generator().manual_seed(1)
    x = (torch.rand(2, 4, 32, 32, generator=g) < 0.15).float()
    opt = torch.optim.Adam(m.parameters(), lr=3e-3)
    first = None
    for _ in range(60):
        loss, _, _ = m.loss(x, gamma=0.0)
        opt.zero_grad()
        loss.backward()
        opt.step()
        first = first if first is not None else loss.item()
    assert loss.item() < 0.6 * first
