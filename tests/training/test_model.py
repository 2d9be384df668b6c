"""VecSet backbone, C-VAE-I/II, losses and configs (vnc_warp.training.model / losses / config)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from vnc_warp.training.config import TrainConfig, load_config, named_config
from vnc_warp.training.losses import (
    GradientQueries,
    cvae_loss,
    eikonal_loss,
    gradient_queries,
    kl_prior_logvar,
    kl_weight_at,
    select_eikonal_queries,
    tsdf_loss,
)
from vnc_warp.training.model import (
    CVAE1,
    CVAE2,
    Attention,
    AttentionBlock,
    DiagonalGaussian,
    FourierEmbedder,
    KLBottleneck,
    LatentDecoder,
    LatentModulator,
    PointEncoder,
    QueryDecoder,
    TimeEmbedding,
    VecSetVAE,
    build_model,
    farthest_point_sample,
    timestep_embedding,
)
from vnc_warp.training.synthetic import EllipsoidTrajectories, ellipsoid_sdf

TINY = dict(width=32, heads=4, num_latents=16, latent_dim=8, encoder_depth=1, decoder_depth=1, num_freqs=4,
            chunk_size=50)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def tdevice(device):
    """Torch device for the Warp device fixture; skips CUDA when this torch build has none."""
    if device.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip("torch has no CUDA")
    return torch.device(device)


def _surface(b: int, n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(b, n, 3, generator=g) * 1.6 - 0.8
    nrm = torch.nn.functional.normalize(torch.randn(b, n, 3, generator=g), dim=-1)
    return torch.cat([xyz, nrm], -1)


def _fps_numpy(points: np.ndarray, m: int, start: int) -> list[int]:
    """Brute force: recompute every point's distance to the whole selected set at each step."""
    chosen = [start]
    for _ in range(m - 1):
        d = np.linalg.norm(points[:, None, :] - points[chosen][None, :, :], axis=-1).min(1)
        chosen.append(int(np.argmax(d)))
    return chosen


def test_fps_matches_bruteforce(tdevice):
    """Batched torch FPS picks exactly the indices of a brute-force NumPy FPS, for given and default starts."""
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(3, 300, 3)).astype(np.float32)
    start = torch.tensor([0, 17, 299])
    got = farthest_point_sample(torch.from_numpy(pts).to(tdevice), 40, start=start.to(tdevice)).cpu()
    for b in range(3):
        assert got[b].tolist() == _fps_numpy(pts[b].astype(np.float64), 40, int(start[b]))
    default = farthest_point_sample(torch.from_numpy(pts).to(tdevice), 40).cpu()
    assert default[0].tolist() == _fps_numpy(pts[0].astype(np.float64), 40, 0)
    torch.manual_seed(5)
    r1 = farthest_point_sample(torch.from_numpy(pts), 10, random_start=True)
    torch.manual_seed(5)
    r2 = farthest_point_sample(torch.from_numpy(pts), 10, random_start=True)
    assert torch.equal(r1, r2) and r1.dtype == torch.int64 and r1.shape == (3, 10)


def test_fps_full_permutation_and_errors():
    """Sampling all N points yields a permutation; too many samples or bad shapes raise ValueError."""
    pts = torch.randn(2, 25, 3)
    idx = farthest_point_sample(pts, 25)
    assert all(sorted(row.tolist()) == list(range(25)) for row in idx)
    with pytest.raises(ValueError, match="num_samples"):
        farthest_point_sample(pts, 26)
    with pytest.raises(ValueError, match=r"\(B, N, 3\)"):
        farthest_point_sample(pts[..., :2], 4)


def test_fourier_and_time_embeddings():
    """Fourier features equal (x, sin(2^k x), cos(2^k x)); time features are cos/sin of the scaled t."""
    emb = FourierEmbedder(num_freqs=3)
    x = torch.tensor([[0.3, -0.2, 0.7]])
    f = emb(x)
    assert f.shape == (1, emb.out_dim) == (1, 21)
    xf = torch.stack([x[0] * 2.0**k for k in range(3)], -1).flatten()  # channel-major: x0*1, x0*2, x0*4, x1*1...
    assert torch.allclose(f[0], torch.cat([x[0], xf.sin(), xf.cos()]))
    te = timestep_embedding(torch.tensor([0.0, 0.5]), 8)
    assert te.shape == (2, 8)
    assert torch.allclose(te[0], torch.tensor([1.0] * 4 + [0.0] * 4))
    assert math.isclose(float(te[1, 0]), math.cos(500.0), rel_tol=1e-5)
    tok = TimeEmbedding(16, num_tokens=3, freq_dim=8)(torch.tensor([0.1, 0.9]))
    assert tok.shape == (2, 3, 16) and tok.dtype == torch.float32
    # neighbouring stages of a 32-stage trajectory get nearly the same features (|d feature| <= scale * dt)
    t = torch.linspace(0.0, 1.0, 33)
    feats = timestep_embedding(t, 256, scale=TimeEmbedding(16).scale)
    assert float((feats[1:] - feats[:-1]).abs().max()) <= 10.0 / 32 + 1e-6
    assert float((timestep_embedding(t, 256)[1:] - timestep_embedding(t, 256)[:-1]).abs().max()) > 1.0


def test_attention_matches_explicit_softmax():
    """One Attention class: self- and cross-attention equal softmax(q k^T / sqrt(d)) v written out by hand."""
    torch.manual_seed(0)
    for context_dim in (None, 12):
        att = Attention(16, heads=2, context_dim=context_dim, qk_norm=False).eval()
        x = torch.randn(2, 5, 16)
        ctx = None if context_dim is None else torch.randn(2, 7, context_dim)
        src = x if ctx is None else ctx
        q = att.to_q(x).view(2, 5, 2, 8).transpose(1, 2)
        k, v = att.to_kv(src).view(2, src.shape[1], 2, 2, 8).permute(2, 0, 3, 1, 4)
        w = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(8), dim=-1)
        ref = att.proj((w @ v).transpose(1, 2).reshape(2, 5, 16))
        assert torch.allclose(att(x, ctx), ref, atol=1e-5)


def test_blocks_and_parts_shapes(tdevice):
    """Shapes and dtypes through every part: blocks, encoder (with/without condition), bottleneck, decoders."""
    torch.manual_seed(0)
    emb = FourierEmbedder(num_freqs=4)
    s = _surface(2, 64).to(tdevice)
    blk = AttentionBlock(32, heads=4).to(tdevice)
    x = torch.randn(2, 10, 32, device=tdevice)
    assert blk(x).shape == (2, 10, 32)
    with pytest.raises(ValueError, match="self-attention"):
        blk(x, x)
    enc = PointEncoder(embedder=emb, width=32, heads=4, num_latents=16, depth=2).to(tdevice)
    h = enc(s)
    assert h.shape == (2, 16, 32) and h.dtype == torch.float32
    cenc = PointEncoder(embedder=emb, width=32, heads=4, num_latents=16, depth=2, condition_dim=24).to(tdevice)
    assert len(cenc.condition) == 3
    assert cenc(s, condition=torch.randn(2, 3, 24, device=tdevice)).shape == (2, 16, 32)
    with pytest.raises(ValueError, match="condition"):
        cenc(s)
    post = KLBottleneck(32, latent_dim=8).to(tdevice).posterior(h)
    assert post.mean.shape == post.logvar.shape == (2, 16, 8) and post.kl().shape == (2,)
    dec = LatentDecoder(embedder=emb, width=32, heads=4, depth=2, chunk_size=7).to(tdevice)
    q = torch.rand(2, 30, 3, device=tdevice) * 2 - 1
    out = dec(h, q)
    assert out.shape == (2, 30) and torch.count_nonzero(out) == 0  # zero-initialised head
    qd = QueryDecoder(embedder=emb, width=32, heads=4, chunk_size=7).to(tdevice)
    torch.nn.init.normal_(qd.head.weight)
    assert torch.allclose(qd(h, q), qd(h, q, chunk_size=1000), atol=1e-5)  # chunking does not change values


def test_diagonal_gaussian_kl_matches_torch():
    """KL(q || N(0, I)) averaged over entries equals torch.distributions' closed form."""
    mean, logvar = torch.randn(3, 4, 5), torch.randn(3, 4, 5)
    q = DiagonalGaussian(mean, logvar)
    ref = torch.distributions.kl_divergence(torch.distributions.Normal(mean, (0.5 * logvar).exp()),
                                            torch.distributions.Normal(0.0, 1.0)).flatten(1).mean(1)
    assert torch.allclose(q.kl(), ref, atol=1e-6)
    torch.manual_seed(0)
    samples = torch.stack([DiagonalGaussian(mean, logvar).sample() for _ in range(4000)])
    assert torch.allclose(samples.std(0), q.std, rtol=0.1)


def test_kl_prior_contracts_toward_t0():
    """The temporal beta_kl curriculum (defect 3 of issue 24): the KL against N(0, s^2 I) equals torch's closed
    form; the prior is N(0, I) at t = 1 and N(0, I / R) at t = 0; the pull on a code's mean (gradient of the KL)
    is R times stronger at t = 0 than at t = 1, and the KL's optimal posterior spread at t = 0 is the prior's
    (std 1 / sqrt(R)), not the std 1 that a heavier weight on N(0, I) would ask for."""
    mean, logvar = torch.randn(3, 4, 5), torch.randn(3, 4, 5)
    pl = torch.tensor([0.0, -1.0, -3.0])
    ref = torch.distributions.kl_divergence(
        torch.distributions.Normal(mean, (0.5 * logvar).exp()),
        torch.distributions.Normal(0.0, (0.5 * pl).exp()[:, None, None].expand_as(mean))).flatten(1).mean(1)
    assert torch.allclose(DiagonalGaussian(mean, logvar).kl(pl), ref, atol=1e-5)
    cfg = dataclasses.replace(named_config("tiny").loss, kl_time_ratio=100.0)
    np.testing.assert_allclose(kl_prior_logvar(torch.tensor([1.0, 0.5, 0.0]), cfg).numpy(),
                               [0.0, -0.5 * math.log(100.0), -math.log(100.0)], atol=1e-6)
    assert torch.equal(kl_prior_logvar(torch.tensor([0.0, 1.0]), dataclasses.replace(cfg, kl_time_ratio=1.0)),
                       torch.zeros(2))
    mu = torch.full((2, 4, 3), 0.5, requires_grad=True)
    lv = torch.full((2, 4, 3), -2.0, requires_grad=True)
    kl = DiagonalGaussian(mu, lv).kl(kl_prior_logvar(torch.tensor([0.0, 1.0]), cfg))
    g_mu, g_lv = torch.autograd.grad(kl.sum(), (mu, lv))
    assert float(g_mu[0, 0, 0] / g_mu[1, 0, 0]) == pytest.approx(100.0, rel=1e-5)
    # d KL / d logvar = 0.5 (e^lv / s^2 - 1) / (M C): zero at lv = log s^2
    assert float(g_lv[0, 0, 0]) == pytest.approx(0.5 * (math.exp(-2.0) * 100.0 - 1.0) / 12, rel=1e-5)
    assert float(g_lv[1, 0, 0]) == pytest.approx(0.5 * (math.exp(-2.0) - 1.0) / 12, rel=1e-5)


def test_surface_and_normal_terms_on_analytic_spheres():
    """L_surf and L_normal against analytic SDFs of a sphere of radius 0.5 (defect 5 of issue 24): the exact SDF
    at points on the sphere with outward normals scores 0 and 0; the SDF shifted by 0.05 scores L_surf = 0.05;
    inward normals score L_normal = 2; the weighted L_tsdf and the gradient points follow the batch."""
    torch.manual_seed(0)
    b, q, s = 2, 40, 30
    n = torch.nn.functional.normalize(torch.randn(b, s, 3), dim=-1)
    batch = {"queries": torch.rand(b, q, 3) * 2 - 1, "near": torch.rand(b, q) < 0.5,
             "on_surface": torch.cat([0.5 * n, n], -1), "tsdf": torch.zeros(b, q), "t": torch.rand(b)}
    cfg = dataclasses.replace(named_config("tiny").loss, eikonal_queries=10, surface_weight=1.0, normal_weight=0.1)
    grad_q = gradient_queries(batch, cfg)
    assert isinstance(grad_q, GradientQueries) and grad_q.points.shape == (b, 10 + s, 3)
    assert grad_q.points.requires_grad and grad_q.num_surface == s and grad_q.near[:, 10:].all()

    def terms(offset: float, flip: float) -> dict:
        gq = GradientQueries(grad_q.points, grad_q.near, flip * grad_q.normals)
        out = {"tsdf": batch["queries"].norm(dim=-1) - 0.5, "mean": torch.zeros(b, 4, 2), "logvar": torch.zeros(b, 4, 2),
               "eikonal_tsdf": gq.points.norm(dim=-1) - 0.5 + offset}
        return {k: v.detach() for k, v in cvae_loss(out, batch, cfg, step=0, gradient=gq).items()}

    exact = terms(0.0, 1.0)
    assert float(exact["surf"]) < 1e-7 and float(exact["normal"]) < 1e-6 and float(exact["eik"]) < 1e-6
    assert float(terms(0.05, 1.0)["surf"]) == pytest.approx(0.05, rel=1e-5)
    assert float(terms(0.0, -1.0)["normal"]) == pytest.approx(2.0, rel=1e-5)
    err = (batch["queries"].norm(dim=-1) - 0.5).abs()
    w = torch.where(batch["near"], 4.0, 1.0)
    weighted = tsdf_loss(batch["queries"].norm(dim=-1) - 0.5, torch.zeros(b, q), near=batch["near"], near_weight=4.0)
    assert float(weighted) == pytest.approx(float((w * err).sum() / w.sum()), rel=1e-6)
    with pytest.raises(ValueError, match="on_surface"):
        gradient_queries({k: v for k, v in batch.items() if k != "on_surface"}, cfg)


@pytest.mark.parametrize("kind", ["vae", "cvae1", "cvae2"])
def test_models_forward_shapes(kind, tdevice):
    """encode/decode/forward shapes and dtypes of the three models; C-VAEs insist on t."""
    torch.manual_seed(0)
    if kind == "vae":
        model = VecSetVAE(**TINY)
    elif kind == "cvae1":
        model = CVAE1(time_tokens=2, time_freq_dim=16, **TINY)
    else:
        model = CVAE2(base=VecSetVAE(**TINY), time_tokens=2, time_freq_dim=16, modulator_depth=1)
    model.to(tdevice)
    s, q = _surface(3, 40).to(tdevice), torch.rand(3, 120, 3, device=tdevice) * 2 - 1
    t = torch.tensor([0.0, 0.5, 1.0], device=tdevice)
    out = model(s, q, t)
    assert out["tsdf"].shape == (3, 120) and out["tsdf"].dtype == torch.float32
    assert out["mean"].shape == out["logvar"].shape == out["z"].shape == (3, 16, 8)
    eq = q[:, :10].clone().requires_grad_(True)
    assert model(s, q, t, eikonal_queries=eq)["eikonal_tsdf"].shape == (3, 10)
    model.eval()
    z, post = model.encode(s, t)
    assert torch.equal(z, post.mean)  # eval: posterior mean, deterministic
    assert model.decode(z, q).shape == (3, 120)
    assert model.time_conditioned == (kind != "vae")
    if kind != "vae":
        with pytest.raises(ValueError, match="pass t"):
            model(s, q)
        with pytest.raises(ValueError, match="t must be"):
            model(s, q, torch.zeros(2, device=tdevice))
    with pytest.raises(ValueError, match=r"\(B, N, 6\)"):
        model(s[..., :3], q, t)


def test_cvae1_latents_depend_on_time():
    """C-VAE-I: the same surface encodes to different latents at different t (time enters the encoder)."""
    torch.manual_seed(0)
    model = CVAE1(time_tokens=2, time_freq_dim=16, **TINY).eval()
    s = _surface(1, 40)
    z0, _ = model.encode(s, 0.0)
    z1, _ = model.encode(s, 1.0)
    assert (z0 - z1).abs().max() > 1e-3


def test_cvae2_starts_as_base_and_modulates():
    """C-VAE-II at initialisation reproduces the frozen VAE's latents at every t; a modulator change
    makes them t-dependent."""
    torch.manual_seed(0)
    base = VecSetVAE(**TINY).eval()
    s = _surface(1, 40)
    ref, _ = base.encode(s)
    model = CVAE2(base=base, time_tokens=2, time_freq_dim=16, modulator_depth=1).eval()
    for t in (0.0, 0.3, 1.0):
        z, _ = model.encode(s, t)
        assert torch.allclose(z, ref, atol=1e-6)
    torch.nn.init.normal_(model.modulator.proj_out.weight, std=0.1)
    assert (model.encode(s, 0.0)[0] - model.encode(s, 1.0)[0]).abs().max() > 1e-3
    with pytest.raises(ValueError, match="plain"):
        CVAE2(base=CVAE1(time_tokens=2, **TINY))


def test_cvae2_encoder_frozen_through_a_step():
    """C-VAE-II: after loss.backward() and an AdamW step the frozen encoder has no grads and unchanged
    weights, while the time embedding, modulator, post projection and decoder do train."""
    torch.manual_seed(0)
    model = CVAE2(base=VecSetVAE(**TINY), time_tokens=2, time_freq_dim=16, modulator_depth=1).train()
    with torch.no_grad():  # a non-zero head so that gradients reach every trainable part
        torch.nn.init.normal_(model.decoder.queries.head.weight, std=0.1)
        torch.nn.init.normal_(model.modulator.proj_out.weight, std=0.1)
    frozen = {k: v.clone() for k, v in model.frozen.state_dict().items()}
    trainable = {n: p.clone() for n, p in model.named_parameters() if p.requires_grad}
    assert trainable and all(n.split(".")[0] in ("post", "decoder", "time_embed", "modulator") for n in trainable)
    assert not any(p.requires_grad for p in model.frozen.parameters())
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-2)
    s, q = _surface(2, 40), torch.rand(2, 50, 3) * 2 - 1
    out = model(s, q, torch.tensor([0.2, 0.8]))
    (out["tsdf"].square().mean() + DiagonalGaussian(out["mean"], out["logvar"]).kl().mean()).backward()
    assert all(p.grad is None for p in model.frozen.parameters())
    opt.step()
    assert all(torch.equal(frozen[k], v) for k, v in model.frozen.state_dict().items())
    moved = {n for n, p in model.named_parameters() if p.requires_grad and not torch.equal(p, trainable[n])}
    for part in ("post", "decoder", "time_embed", "modulator"):
        assert any(n.startswith(part + ".") for n in moved), part
    assert not model.frozen.training and model.training


def test_latent_modulator_identity_at_init():
    """At initialisation z_ctl's mean is the frozen z_geo's and its log-variance is the modulator's own
    ``logvar_init``, whatever the frozen encoder's log-variance (defect 2 of issue 24: a frozen spread of ~1 was
    inherited, so C-VAE-II trained its decoder on noise)."""
    mod = LatentModulator(latent_dim=8, width=32, heads=4, depth=2, logvar_init=-6.0)
    prior = DiagonalGaussian(torch.randn(2, 5, 8), torch.zeros(2, 5, 8))
    post = mod(prior, torch.randn(2, 3, 32))
    assert torch.equal(post.mean, prior.mean)
    assert torch.equal(post.logvar, torch.full_like(prior.logvar, -6.0))


def test_bottleneck_starts_narrow():
    """The KL bottleneck's posterior starts at log-variance ``logvar_init`` for any features (defect 1 of issue
    24: it started near 0, so training decoded codes with std ~1 around the mean that inference decodes)."""
    torch.manual_seed(0)
    post = KLBottleneck(32, latent_dim=8).posterior(torch.randn(2, 16, 32) * 5)
    assert torch.equal(post.logvar, torch.full_like(post.logvar, -8.0))
    assert float(post.std.max().detach()) < 0.02 and float(post.mean.abs().max().detach()) > 0.1


def test_eikonal_loss_analytic_sphere():
    """Eikonal term on analytic SDFs: the exact sphere SDF (|grad| = 1) gives ~0; s * SDF gives (s - 1)^2,
    and its derivative w.r.t. s (through create_graph) is 2 (s - 1)."""
    torch.manual_seed(0)
    q = (torch.rand(2, 200, 3) * 2 - 1).requires_grad_(True)
    near = torch.rand(2, 200) < 0.5
    exact = q.norm(dim=-1) - 0.5
    assert float(eikonal_loss(exact, q, near).detach()) < 1e-10
    s = torch.tensor(1.7, requires_grad=True)
    loss = eikonal_loss(s * (q.norm(dim=-1) - 0.5), q, near)
    assert math.isclose(float(loss.detach()), 0.7**2, rel_tol=1e-5)
    (ds,) = torch.autograd.grad(loss, s)
    assert math.isclose(float(ds), 2 * 0.7, rel_tol=1e-4)
    assert float(eikonal_loss(s * exact, q, torch.zeros_like(near)).detach()) == 0.0
    with pytest.raises(ValueError, match="require grad"):
        eikonal_loss(exact.detach(), q.detach(), near)


def test_select_eikonal_queries_prefers_near():
    """The eikonal subset holds all near queries first (when there are enough) and points that require grad."""
    q = torch.rand(2, 50, 3)
    near = torch.zeros(2, 50, dtype=torch.bool)
    near[0, :30] = True
    near[1, 40:] = True
    pts, mask = select_eikonal_queries(q, near, 20)
    assert pts.shape == (2, 20, 3) and pts.requires_grad
    assert mask[0].all() and int(mask[1].sum()) == 10


def test_tsdf_loss_and_kl_schedule():
    """L1/MSE against hand-computed values; the beta_kl curriculum ramps linearly and then holds."""
    p, t = torch.tensor([[0.1, -0.3]]), torch.tensor([[0.0, 0.1]])
    assert math.isclose(float(tsdf_loss(p, t)), (0.1 + 0.4) / 2, rel_tol=1e-6)
    assert math.isclose(float(tsdf_loss(p, t, kind="mse")), (0.01 + 0.16) / 2, rel_tol=1e-6)
    cfg = named_config("tiny").loss
    cfg = dataclasses.replace(cfg, kl_schedule="linear", kl_weight=1e-2, kl_weight_start=1e-4, kl_warmup_start=10,
                              kl_warmup_steps=100)
    assert kl_weight_at(0, cfg) == kl_weight_at(10, cfg) == 1e-4
    assert math.isclose(kl_weight_at(60, cfg), 1e-4 + 0.5 * (1e-2 - 1e-4))
    assert kl_weight_at(110, cfg) == kl_weight_at(10_000, cfg) == 1e-2
    assert kl_weight_at(5, dataclasses.replace(cfg, kl_schedule="constant")) == 1e-2


def test_ellipsoid_sdf_oracle():
    """The synthetic data's exact ellipsoid SDF equals |x| - r on a sphere and a dense-sampling distance otherwise."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, size=(64, 3))
    assert np.allclose(ellipsoid_sdf(x, np.array([0.6, 0.6, 0.6])), np.linalg.norm(x, axis=1) - 0.6, atol=1e-9)
    axes = np.array([0.9, 0.5, 0.35])
    u = rng.normal(size=(400_000, 3))
    dense = axes * u / np.linalg.norm(u, axis=1, keepdims=True)
    q = rng.uniform(-1, 1, size=(40, 3))
    d = np.sqrt(((q[:, None, :] - dense[None, ::40]) ** 2).sum(-1)).min(1)  # 10k dense points, coarse bound
    got = ellipsoid_sdf(q, axes)
    assert np.all(np.abs(got) <= d + 1e-9) and np.allclose(np.abs(got), d, atol=0.02)
    inside = ((q / axes) ** 2).sum(1) < 1
    assert np.array_equal(got < 0, inside)


def test_synthetic_dataset_contract():
    """The synthetic trajectories follow the TrajectoryDataset item contract (keys, shapes, dtypes, ranges)."""
    ds = EllipsoidTrajectories(num_shapes=2, num_stages=3, num_surface=50, num_queries=40)
    it = ds[4]
    assert it["surface"].shape == (50, 6) and it["queries"].shape == (40, 3)
    assert it["tsdf"].shape == (40,) and it["near"].dtype == torch.bool and it["t"].shape == ()
    assert int(it["shape_id"]) == 1 and int(it["stage"]) == 1 and float(it["t"]) == 0.5
    assert torch.allclose(it["surface"][:, 3:].norm(dim=-1), torch.ones(50))
    assert float(it["tsdf"].abs().max()) <= np.float32(0.1) and float(it["queries"].abs().max()) <= 1.2
    assert np.allclose(ds.axes0.max(1), 0.9)  # stage-0 bbox max extent 1.8, the contract's normalisation
    p = it["surface"][:, :3].double().numpy()
    assert np.allclose(((p / ds.axes(1, 0.5)) ** 2).sum(1), 1.0, atol=1e-5)  # on the stage's own surface
    assert ds.item_ids() == [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2)]


def test_configs_roundtrip_and_errors(tmp_path):
    """Configs round-trip through dicts/JSON; unknown keys, bad types and bad values name the key."""
    cfg = named_config("cvae1")
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    assert (cfg.model.num_latents, cfg.model.latent_dim) == (2048, 32)
    assert (named_config("cvae2").model.num_latents, named_config("cvae2").model.latent_dim) == (2048, 64)
    assert named_config("vae").model.kind == "vae" and named_config("vae").data.encoder_input == "item"
    with pytest.raises(ValueError, match="model.widht"):
        TrainConfig.from_dict({"model": {"widht": 3}})
    with pytest.raises(ValueError, match="model.width must be int"):
        TrainConfig.from_dict({"model": {"width": "wide"}})
    with pytest.raises(ValueError, match="multiple of model.heads"):
        TrainConfig.from_dict({"model": {"width": 30, "heads": 4}})
    path = tmp_path / "c.json"
    path.write_text('{"optim": {"lr": 3e-4, "betas": [0.8, 0.9]}}')
    loaded = load_config(path)
    assert loaded.optim.lr == 3e-4 and loaded.optim.betas == (0.8, 0.9)
    with pytest.raises(FileNotFoundError, match="neither a named config"):
        load_config(tmp_path / "missing.json")
    path.write_text("{not json")
    with pytest.raises(ValueError, match="cannot read config JSON"):
        load_config(path)


def test_paper_size_models_on_meta_device():
    """The paper-size models build (on the meta device, no memory) with 2048 x 32 and 2048 x 64 latent sets."""
    with torch.device("meta"):
        m1 = build_model(named_config("cvae1").model)
        m2 = build_model(named_config("cvae2").model, load_pretrained=False)
        s = torch.empty(1, 4096, 6)
        z1, _ = m1.encode(s, 0.5, sample=False)
    assert z1.shape == (1, 2048, 32)
    assert (m2.num_latents, m2.latent_dim) == (2048, 64)
    assert sum(p.numel() for p in m1.parameters()) > 50e6
