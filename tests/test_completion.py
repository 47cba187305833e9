"""Tests of comgs_dr.lighting.completion: size, shapes/range, spherical padding (seam
equivariance, polar neighbours), EV embedding, blend of observed pixels, gradcheck of the
padding and FiLM blocks, determinism, save/load and the NumPy backend."""
import dataclasses

import numpy as np
import pytest
import torch

from comgs_dr.lighting import completion as C

torch.set_num_threads(1)

SMALL = C.CompletionConfig(base_channels=8, channel_mults=(1, 2, 2, 2, 2), embed_dim=16)


def inputs(h=32, w=64, b=1, dtype=torch.float32, seed=0, coverage=0.6):
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(b, 3, h, w, generator=g, dtype=dtype)
    normal = torch.nn.functional.normalize(torch.randn(b, 3, h, w, generator=g, dtype=dtype), dim=1)
    mask = (torch.rand(b, 1, h, w, generator=g, dtype=dtype) < coverage).to(dtype)
    return rgb, normal, mask


def net(config=None, seed=0):
    torch.manual_seed(seed)
    m = C.CompletionNet(config).eval()
    with torch.no_grad():   # FiLM starts at identity; randomise so conditioning matters
        for mod in m.modules():
            if isinstance(mod, C.FiLM):
                mod.lin.weight.normal_(0, 0.2)
                mod.lin.bias.normal_(0, 0.2)
    return m


@pytest.fixture(scope="module")
def default_net():
    return net()


def test_parameter_count(default_net):
    n = C.count_parameters(default_net)
    assert 1_000_000 <= n <= 10_000_000, n
    assert C.count_parameters(net(SMALL)) < n


def test_output_shape_range_finite(default_net):
    rgb, normal, mask = inputs(b=2)
    rgb[:, :, :4] = float("nan")          # garbage in holes must not leak
    mask[:, :, :4] = 0
    with torch.no_grad():
        out = default_net(rgb, normal, mask[:, 0], torch.tensor([0.0, -5.0]), torch.tensor([0, 1]))
    for t in out:
        assert t.shape == (2, 3, 32, 64)
        assert torch.isfinite(t).all()
        assert t.min() >= 0 and t.max() <= 1


def test_bad_sizes_rejected(default_net):
    with pytest.raises(ValueError, match="multiple"):
        default_net(*inputs(h=32, w=48))
    with pytest.raises(ValueError, match="labels"):
        default_net(*inputs(), 0.0, 3)


@pytest.mark.parametrize("padding", ["polar", "replicate"])
def test_horizontal_shift_equivariance(padding):
    cfg = C.CompletionConfig(padding=padding) if padding == "polar" else \
        C.CompletionConfig(**{**SMALL.to_dict(), "padding": padding})
    m = net(cfg).double()
    rgb, normal, mask = inputs(dtype=torch.float64)
    step = 2 ** cfg.levels
    with torch.no_grad():
        ref = m(rgb, normal, mask, -2.5, 1).pred
        for s in (step, 3 * step):
            r = [torch.roll(a, s, dims=-1) for a in (rgb, normal, mask)]
            out = m(*r, -2.5, 1).pred
            assert torch.allclose(out, torch.roll(ref, s, dims=-1), atol=1e-10, rtol=0)


def test_polar_padding_neighbours():
    x = torch.arange(4 * 8, dtype=torch.float64).reshape(1, 1, 4, 8)
    p = C.SphericalPad2d(2, "polar")(x)[0, 0]
    assert p.shape == (8, 12)
    core = x[0, 0]
    assert torch.equal(p[2:6, 2:10], core)
    for k in range(2):                      # row -1-k is row k shifted by half a turn
        assert torch.equal(p[1 - k, 2:10], torch.roll(core[k], 4))
        assert torch.equal(p[6 + k, 2:10], torch.roll(core[3 - k], 4))
    assert torch.equal(p[:, :2], p[:, 8:10]) and torch.equal(p[:, 10:], p[:, 2:4])  # circular
    r = C.SphericalPad2d(1, "replicate")(x)[0, 0]
    assert torch.equal(r[0, 1:9], core[0]) and torch.equal(r[5, 1:9], core[3])
    with pytest.raises(ValueError, match="even width"):
        C.SphericalPad2d(1)(torch.zeros(1, 1, 4, 7))


def test_ev_embedding_linearity():
    torch.manual_seed(3)
    emb = C.EVEmbedding(64)
    xb, xd = emb.xi_b.detach(), emb.xi_d.detach()
    e = emb(torch.tensor([0.0, -2.5, -5.0])).detach()
    assert torch.equal(e[0], xb)
    assert torch.equal(e[2], xd)
    assert torch.equal(e[1], (xb + xd) / 2)
    # the paper's formula, at any EV (extrapolation included)
    evs = torch.tensor([-1.0, -3.7, 1.0, -7.0])
    want = xb + (evs / C.EV_MIN)[:, None] * (xd - xb)
    assert torch.allclose(emb(evs).detach(), want, atol=1e-6)


def test_blend_keeps_observed_pixels(default_net):
    rgb, normal, mask = inputs()
    rgb = rgb * 0.9                          # nothing saturated
    rgb[0, :, 0, 0] = 1.0                   # one saturated observed pixel
    rgb[0, 0, 0, 1] = 1.0                   # one with only its red channel clipped
    mask[0, 0, 0, :2] = 1.0
    res = default_net.complete(rgb, normal, mask, label=0)
    assert sorted(res) == [-5.0, -2.5, 0.0]
    seen = mask.expand_as(rgb) > 0
    assert torch.equal(res[0.0][seen], rgb[seen])
    # EV < 0: observed pixels re-exposed with clip(sRGB(linear * 2**ev)) ...
    lin = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
    for ev in (-2.5, -5.0):
        x = lin * 2.0 ** ev
        want = torch.as_tensor(np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055))
        ok = seen.clone()
        ok[0, :, 0, 0] = False
        ok[0, 0, 0, 1] = False
        assert torch.allclose(res[ev][ok], want[ok], atol=1e-5)
        # ... except saturated channels, whose radiance is only bounded below by the clip:
        # the prediction, raised to that bound where it is darker
        pred = default_net(rgb, normal, mask, ev, 0).pred
        for y, x, c in ((0, 0, 0), (0, 0, 1), (0, 0, 2), (0, 1, 0)):
            bound = float(want[0, c, y, x])
            assert res[ev][0, c, y, x].item() == pytest.approx(max(pred[0, c, y, x].item(), bound))
    holes = ~seen
    assert not torch.equal(res[0.0][holes], rgb[holes])


def test_gradcheck_padding():
    x = torch.randn(1, 2, 4, 6, dtype=torch.float64, requires_grad=True)
    for pad, vert in ((1, "polar"), (2, "polar"), (1, "replicate")):
        assert torch.autograd.gradcheck(C.SphericalPad2d(pad, vert), (x,))


def test_gradcheck_film_and_resblock():
    torch.manual_seed(0)
    film = C.FiLM(3, 4).double()
    torch.nn.init.normal_(film.lin.weight)
    x = torch.randn(2, 4, 3, 4, dtype=torch.float64, requires_grad=True)
    cond = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(film, (x, cond))
    blk = C.ResBlock(4, 6, 3, groups=2).double()
    torch.nn.init.normal_(blk.film.lin.weight)
    assert torch.autograd.gradcheck(blk, (x, cond))


def test_eval_determinism(default_net):
    rgb, normal, mask = inputs(seed=5)
    a = default_net.complete(rgb, normal, mask, label=1)
    b = default_net.complete(rgb, normal, mask, label=1)
    assert all(torch.equal(a[k], b[k]) for k in a)
    # conditioning matters: EV and label change the prediction
    with torch.no_grad():
        p = [default_net(rgb, normal, mask, ev, lab).pred for ev, lab in ((0, 1), (-5, 1), (0, 0))]
    assert not torch.allclose(p[0], p[1]) and not torch.allclose(p[0], p[2])


def test_save_load_roundtrip_and_errors(tmp_path):
    m = net(SMALL, seed=7)
    path = C.save_weights(m, tmp_path / "w" / "completion.pt")
    m2 = C.load_weights(path, config=SMALL)
    assert m2.config == SMALL and not m2.training
    rgb, normal, mask = inputs(seed=2)
    with torch.no_grad():
        assert torch.equal(m(rgb, normal, mask, -2.5, 2).completed,
                           m2(rgb, normal, mask, -2.5, 2).completed)

    with pytest.raises(FileNotFoundError, match="not found"):
        C.load_weights(tmp_path / "missing.pt")

    ckpt = torch.load(path, weights_only=True)
    bad = tmp_path / "old.pt"
    torch.save({**ckpt, "version": "comgs-completion-v0"}, bad)
    with pytest.raises(C.WeightsError, match="version"):
        C.load_weights(bad)

    with pytest.raises(C.WeightsError, match="config mismatch.*base_channels"):
        C.load_weights(path, config=C.CompletionConfig())
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(C.WeightsError, match="not a readable"):
        C.load_weights(junk)
    import pickle
    foreign = tmp_path / "foreign.pt"                    # a pickle torch refuses to unpickle
    from pathlib import PurePosixPath
    for obj in (object(), {"x": PurePosixPath("a")}):      # an opcode / a global torch refuses
        foreign.write_bytes(pickle.dumps(obj, protocol=2))
        with pytest.raises(C.WeightsError, match="not a readable") as e:
            C.load_weights(foreign)
        msg = str(e.value)                                  # the reason, not the advice
        assert "UnpicklingError: " in msg and "\n" not in msg
        assert not any(w in msg for w in ("weights_only", "safe_globals", "Please"))
    tampered = tmp_path / "tampered.pt"
    torch.save({**ckpt, "config": {**ckpt["config"], "base_channels": 16}}, tampered)
    with pytest.raises(C.WeightsError, match="state dict"):
        C.load_weights(tampered)


def test_network_backend_non_multiple_size():
    m = net(SMALL, seed=1)
    rng = np.random.default_rng(0)
    h, w = 30, 60
    rgb = rng.uniform(0, 0.9, (h, w, 3)).astype(np.float32)
    normal = rng.normal(size=(h, w, 3)).astype(np.float32)
    mask = (rng.uniform(size=(h, w)) < 0.5).astype(np.float32)
    rgb[mask == 0] = np.nan
    assert C.NetworkBackend(m).net_size(h, w) == m.config.train_resolution   # default
    backend = C.NetworkBackend(m, resolution="input")
    assert isinstance(backend, C.CompletionBackend)
    assert backend.net_size(h, w) == (32, 64)
    out = backend.complete(rgb, normal, mask, label=1)
    assert sorted(out) == [-5.0, -2.5, 0.0]
    for img in out.values():
        assert img.shape == (h, w, 3) and img.dtype == np.float32
        assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 1
    np.testing.assert_array_equal(out[0.0][mask > 0], rgb[mask > 0])
    assert out[-5.0][mask > 0].mean() < 0.5 * out[0.0][mask > 0].mean()
    fixed = C.NetworkBackend(m, resolution=(64, 128)).complete(rgb, normal, mask[..., None], (0.0,))
    assert fixed[0.0].shape == (h, w, 3)
    with pytest.raises(ValueError, match="mask"):
        backend.complete(rgb, normal, mask[:10])


def test_resize_equirect_wraps():
    x = torch.zeros(1, 1, 2, 4, dtype=torch.float64)
    x[..., 0] = 1.0
    y = C.resize_equirect(x, 2, 8)
    # left edge of the map blends with the right (u wraps), right edge with the left
    assert y[0, 0, 0, 0] == 0.75 and y[0, 0, 0, -1] == 0.25
    assert torch.equal(C.resize_equirect(x, 2, 4), x)


def test_push_pull_prior_residual_starts_at_the_prior():
    """prior='push_pull': the output conv is zero at init, so pred is the push-pull fill
    re-exposed to each EV; gradients reach the residual."""
    from comgs_dr.lighting.hdr import push_pull_fill
    m = net(dataclasses.replace(SMALL, prior="push_pull"), seed=2)
    g = torch.Generator().manual_seed(3)
    rgb = torch.rand(2, 3, 16, 32, generator=g)
    mask = (torch.rand(2, 1, 16, 32, generator=g) > 0.4).float()
    prior = C.fill_prior(rgb, mask)
    ref = push_pull_fill(rgb[0].permute(1, 2, 0).numpy(), mask[0, 0].numpy())
    np.testing.assert_allclose(prior[0].permute(1, 2, 0).numpy(), np.clip(ref, 0, 1), atol=1e-6)
    ev = torch.tensor([0.0, -2.5])
    out = m(rgb, torch.zeros_like(rgb), mask, ev, 1)
    base = C.expose_ldr(prior, ev).clamp(1e-3, 1 - 1e-3)
    torch.testing.assert_close(out.pred, base, atol=1e-6, rtol=0)
    out.pred.sum().backward()
    assert m.out_conv.conv.weight.grad.abs().sum() > 0
    # nothing observed: a mid-grey prior, finite output
    empty = m(rgb, torch.zeros_like(rgb), torch.zeros_like(mask), 0.0, 2)
    assert torch.isfinite(empty.pred).all()
    assert torch.allclose(C.fill_prior(rgb, torch.zeros_like(mask)), torch.tensor(0.5))


def test_v1_checkpoints_still_load(tmp_path):
    m = net(SMALL, seed=4)
    path = C.save_weights(m, tmp_path / "v1.pt")
    ck = torch.load(path, weights_only=True)
    cfg = {k: v for k, v in ck["config"].items() if k not in ("prior", "train_resolution")}
    ck["config"] = {**cfg, "version": "comgs-completion-v1"}
    ck["version"] = "comgs-completion-v1"
    torch.save(ck, path)
    loaded = C.load_weights(path)
    assert loaded.config.prior == "none" and loaded.config.version == "comgs-completion-v1"
    ck["version"] = "comgs-completion-v0"
    torch.save(ck, path)
    with pytest.raises(C.WeightsError, match="not supported"):
        C.load_weights(path)



def test_load_torch_file_names_the_file_and_the_problem(tmp_path):
    """lighting.torch_io.load_torch_file: the one weights_only loader behind the completion
    net, the light head, the diffusion embeddings and train-completion's checkpoints."""
    from comgs_dr.lighting.torch_io import load_torch_file
    good = tmp_path / "good.pt"
    torch.save({"format": "fmt/1", "x": torch.arange(3)}, good)
    assert torch.equal(load_torch_file(good, "fmt/1", "thing")["x"], torch.arange(3))
    with pytest.raises(ValueError, match=r"good\.pt: not a thing \(format 'fmt/2' expected\)"):
        load_torch_file(good, "fmt/2", "thing")
    plain = tmp_path / "plain.pt"
    torch.save([1, 2], plain)
    assert load_torch_file(plain, None, "thing") == [1, 2]          # no format to check
    with pytest.raises(C.WeightsError, match="not a thing .*; start over$"):
        load_torch_file(plain, "fmt/1", "thing", error=C.WeightsError, hint="; start over")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not torch")
    with pytest.raises(ValueError, match=r"junk\.pt: not a readable thing \(\w+Error: "):
        load_torch_file(junk, "fmt/1", "thing")
