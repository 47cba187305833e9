"""Completion backends: baseline fills re-exposed per EV, the network loader, the diffusers
inpainting loop on a tiny random model (no real weights, nothing downloaded)."""
import types

import numpy as np
import pytest
import torch

from comgs_dr.core import colorspace
from comgs_dr.lighting import backends, completion, hdr

H, W = 32, 64
TINY = dict(base_channels=8, levels=2, channel_mults=(1, 2, 2), embed_dim=16, groups=4)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _inputs(seed=0, frac=0.6):
    rng = np.random.default_rng(seed)
    rgb = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    normal = rng.normal(size=(H, W, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    mask = (rng.uniform(size=(H, W)) < frac).astype(np.float32)
    rgb[mask == 0] = np.nan                       # holes may hold anything
    return rgb, normal, mask


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory):
    torch.manual_seed(0)
    net = completion.CompletionNet(completion.CompletionConfig(**TINY))
    return completion.save_weights(net, tmp_path_factory.mktemp("net") / "tiny.pt")


# ---------------------------------------------------------------------------------------
# Fill backends

@pytest.mark.parametrize("kind", backends.FILL_KINDS)
def test_fill_backend_brackets(kind):
    rgb, normal, mask = _inputs()
    out = backends.FillBackend(kind).complete(rgb, normal, mask)
    assert sorted(out) == [-5.0, -2.5, 0.0]
    obs = mask > 0.5
    for ev, img in out.items():
        assert img.shape == (H, W, 3) and img.dtype == np.float32 and np.isfinite(img).all()
        assert img.min() >= 0 and img.max() <= 1
    assert np.array_equal(out[0.0][obs], rgb[obs])                      # observed kept
    # darker brackets are the EV-0 fill re-exposed
    lin = colorspace.srgb_decode(out[0.0].astype(np.float64))
    np.testing.assert_allclose(out[-5.0], hdr.expose(lin, -5.0), atol=1e-6)
    assert out[-5.0].mean() < out[-2.5].mean() < out[0.0].mean()
    # fusing the brackets gives back the decoded fill (float32 rounding only)
    np.testing.assert_allclose(hdr.fuse_brackets(out), lin, rtol=1e-5, atol=1e-6)


def test_fill_backend_kinds_differ_and_match_hdr():
    rgb, normal, mask = _inputs(1)
    outs = {k: backends.FillBackend(k).complete(rgb, normal, mask, evs=(0.0,))[0.0]
            for k in backends.FILL_KINDS}
    hole = mask < 0.5
    assert np.abs(outs["mean"][hole] - outs["push_pull"][hole]).max() > 1e-2
    assert np.abs(outs["sh"][hole] - outs["push_pull"][hole]).max() > 1e-2
    # the mean fill is one constant colour in the holes
    assert np.ptp(outs["mean"][hole], axis=0).max() < 1e-6
    np.testing.assert_allclose(outs["push_pull"], hdr.push_pull_fill(np.nan_to_num(rgb), mask),
                               atol=1e-6)


def test_fill_backend_errors():
    rgb, normal, mask = _inputs()
    with pytest.raises(ValueError, match="unknown kind 'median'"):
        backends.FillBackend("median")
    b = backends.FillBackend("mean")
    with pytest.raises(ValueError, match=r"rgb/normal \[H,W,3\] and mask \[H,W\]"):
        b.complete(rgb[..., :2], normal[..., :2], mask)
    with pytest.raises(ValueError, match="mask"):
        b.complete(rgb, normal, mask[:, :10])
    with pytest.raises(ValueError, match="normal"):
        b.complete(rgb, normal[:4], mask)
    with pytest.raises(ValueError, match="zero coverage"):
        b.complete(rgb, normal, np.zeros_like(mask))


# ---------------------------------------------------------------------------------------
# Network backend

def test_network_backend_from_weights(tiny_weights):
    rgb, normal, mask = _inputs(2)
    b = backends.load_network_backend(tiny_weights, resolution=(H, W))
    assert isinstance(b, completion.NetworkBackend) and b.resolution == (H, W)
    out = b.complete(rgb, normal, mask, label=1)
    again = backends.load_network_backend(tiny_weights, (H, W)).complete(rgb, normal, mask,
                                                                         label=1)
    for ev in (0.0, -2.5, -5.0):
        assert out[ev].shape == (H, W, 3) and np.isfinite(out[ev]).all()
        assert np.array_equal(out[ev], again[ev])                            # deterministic
    obs = mask > 0.5
    assert np.array_equal(out[0.0][obs], rgb[obs])
    assert not np.allclose(out[0.0][~obs], out[-5.0][~obs])                  # EV conditioning
    b2 = backends.load_network_backend(tiny_weights, resolution=(16, 32))
    assert b2.resolution == (16, 32)
    assert np.isfinite(b2.complete(rgb, normal, mask)[-5.0]).all()


def test_network_backend_errors(tiny_weights, tmp_path, monkeypatch):
    assert backends.DEFAULT_WEIGHTS.parts[-3:] == ("lighting", "weights", "completion.pt")
    with pytest.raises(FileNotFoundError, match="comgs train-completion"):
        backends.load_network_backend(tmp_path / "missing.pt")
    monkeypatch.setattr(backends, "DEFAULT_WEIGHTS", tmp_path / "nothing" / "completion.pt")
    with pytest.raises(FileNotFoundError, match="comgs train-completion"):
        backends.load_network_backend()
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(completion.WeightsError):
        backends.load_network_backend(bad)
    rgb, normal, mask = _inputs()
    with pytest.raises(ValueError, match="NetworkBackend"):
        backends.load_network_backend(tiny_weights).complete(rgb, normal[..., :1], mask)


# ---------------------------------------------------------------------------------------
# Diffusers backend

def _tiny_model(in_channels=9):
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    torch.manual_seed(0)
    unet = UNet2DConditionModel(
        sample_size=16, in_channels=in_channels, out_channels=4, block_out_channels=(8, 16),
        layers_per_block=1, down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"), cross_attention_dim=16,
        norm_num_groups=4, attention_head_dim=2)
    vae = AutoencoderKL(block_out_channels=(8, 8), layers_per_block=1, latent_channels=4,
                        down_block_types=("DownEncoderBlock2D",) * 2,
                        up_block_types=("UpDecoderBlock2D",) * 2, norm_num_groups=4)
    return types.SimpleNamespace(unet=unet.eval(), vae=vae.eval(), scheduler=DDIMScheduler())


@pytest.fixture(scope="module")
def tiny_diffusion(tmp_path_factory):
    pytest.importorskip("diffusers")
    pipe = _tiny_model()
    d = tmp_path_factory.mktemp("sd")
    for name in ("unet", "vae", "scheduler"):
        getattr(pipe, name).save_pretrained(d / name)
    g = torch.Generator().manual_seed(1)
    emb = {"xi_b": torch.randn(4, 16, generator=g), "xi_d": torch.randn(4, 16, generator=g)}
    return pipe, d, emb


def test_diffusers_round_trip(tiny_diffusion):
    pipe, d, emb = tiny_diffusion
    rgb, normal, mask = _inputs(3)
    b = backends.DiffusersBackend(d, steps=2, **emb)
    assert b.multiple == 4 and b.net_size(30, 60) == (32, 60)
    out = b.complete(rgb, normal, mask, label="indoor")
    again = b.complete(rgb, normal, mask, label="indoor")
    obs = mask > 0.5
    for ev in (0.0, -2.5, -5.0):
        assert out[ev].shape == (H, W, 3) and out[ev].dtype == np.float32
        assert np.isfinite(out[ev]).all() and out[ev].min() >= 0 and out[ev].max() <= 1
        assert np.array_equal(out[ev], again[ev])                            # fixed seed
    assert np.array_equal(out[0.0][obs], rgb[obs])
    assert np.abs(out[0.0][~obs] - out[-5.0][~obs]).max() > 1e-3           # EV prompt acts
    # the saved model loaded back == the in-memory components (same weights, same loop)
    direct = backends.DiffusersBackend(pipe, steps=2, **emb).complete(rgb, normal, mask)
    for ev in out:
        np.testing.assert_allclose(direct[ev], out[ev], atol=1e-5)
    # a different seed gives a different completion
    other = backends.DiffusersBackend(pipe, steps=2, seed=7, **emb).complete(rgb, normal, mask,
                                                                             evs=(0.0,))
    assert np.abs(other[0.0][~obs] - out[0.0][~obs]).max() > 1e-3


def test_diffusers_ev_embedding_and_from_dir(tiny_diffusion, tmp_path):
    pipe, d, emb = tiny_diffusion
    b = backends.DiffusersBackend(pipe, **emb)
    xb, xd = emb["xi_b"][None], emb["xi_d"][None]
    torch.testing.assert_close(b.ev_embedding(0.0), xb)
    torch.testing.assert_close(b.ev_embedding(-5.0), xd)
    torch.testing.assert_close(b.ev_embedding(-2.5), 0.5 * (xb + xd))
    # ev_embeddings.pt inside the folder is picked up by from_dir
    import shutil
    d2 = tmp_path / "sd"
    shutil.copytree(d, d2)
    torch.save(emb, d2 / backends.DiffusersBackend.EMBEDDINGS_FILE)
    (d2 / "text_encoder").mkdir()                      # unusable without transformers:
    (d2 / "tokenizer").mkdir()                         # skipped, the embeddings are given
    b2 = backends.DiffusersBackend.from_dir(d2, steps=1)
    torch.testing.assert_close(b2.ev_embedding(-1.0), b.ev_embedding(-1.0))
    assert b2.text_encoder is None


def test_diffusers_normals_channels():
    pytest.importorskip("diffusers")
    pipe = _tiny_model(in_channels=13)
    b = backends.DiffusersBackend(pipe, steps=1, xi_b=torch.zeros(4, 16),
                                  xi_d=torch.ones(4, 16))
    assert b.use_normals
    rgb, normal, mask = _inputs(4)
    out = b.complete(rgb, normal, mask, evs=(0.0,))
    out_flip = b.complete(rgb, -normal, mask, evs=(0.0,))
    hole = mask < 0.5
    assert np.isfinite(out[0.0]).all()
    assert np.abs(out[0.0][hole] - out_flip[0.0][hole]).max() > 1e-4          # normals used


def test_diffusers_errors(tiny_diffusion, tmp_path):
    pipe, d, emb = tiny_diffusion
    with pytest.raises(ValueError, match="xi_b and xi_d"):
        backends.DiffusersBackend(pipe, xi_b=emb["xi_b"])
    with pytest.raises(ValueError, match="no text encoder"):
        backends.DiffusersBackend(pipe)
    with pytest.raises(ValueError, match="lacks"):
        backends.DiffusersBackend(types.SimpleNamespace(unet=pipe.unet), **emb)
    with pytest.raises(ValueError, match="differ in shape"):
        backends.DiffusersBackend(pipe, xi_b=torch.zeros(4, 16), xi_d=torch.zeros(5, 16))
    with pytest.raises(FileNotFoundError, match="not found"):
        backends.DiffusersBackend(tmp_path / "nope", **emb)
    (tmp_path / "half" / "unet").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match="'vae/'"):
        backends.DiffusersBackend(tmp_path / "half", **emb)
    with pytest.raises(ValueError, match="input channels"):
        backends.DiffusersBackend(_tiny_model(in_channels=4), **emb)
    with pytest.raises(ValueError, match="multiple of 4"):
        backends.DiffusersBackend(pipe, resolution=(30, 60), **emb)
    rgb, normal, mask = _inputs()
    b = backends.DiffusersBackend(pipe, steps=1, guidance_scale=3.0, **emb)
    with pytest.raises(ValueError, match="negative"):
        b.complete(rgb, normal, mask, evs=(0.0,))
    b = backends.DiffusersBackend(pipe, steps=1, guidance_scale=3.0,
                                  negative=torch.zeros(4, 16), **emb)
    assert np.isfinite(b.complete(rgb, None, mask, evs=(0.0,))[0.0]).all()  # normal optional
    with pytest.raises(ValueError, match="DiffusersBackend"):
        b.complete(rgb[:, :, :1], normal, mask)


def test_diffusers_missing_package(monkeypatch):
    import builtins
    real = builtins.__import__

    def fake(name, *a, **k):
        if name == "diffusers":
            raise ImportError("no diffusers")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake)
    with pytest.raises(ImportError, match="pip install diffusers"):
        backends._import_diffusers()


def _pano(h=16, w=32, seed=0):
    rng = np.random.default_rng(seed)
    rgb = rng.uniform(0.05, 1.0, (h, w, 3)).astype(np.float32)
    rgb[2:4, 5:7] = 1.0                                                  # a clipped light
    mask = np.ones((h, w), np.float32)
    mask[8:, 10:25] = 0.0                                                # the hole
    return rgb, np.zeros_like(rgb), mask


class _Bright(backends.FillBackend):
    """A fill whose EV < 0 brackets hold 8x the EV-0 fill (radiance a fill cannot have)."""

    def complete(self, rgb, normal, mask, evs=completion.DEFAULT_EVS, label=2):
        out = super().complete(rgb, normal, mask, evs, label)
        rad = hdr.unexpose(out[0.0], 0.0) * 8.0
        return {e: (v if e == 0.0 else hdr.expose(rad, e).astype(np.float32))
                for e, v in out.items()}


def test_blend_backend_keeps_the_first_where_seen_and_averages_radiance_in_the_hole():
    rgb, normal, mask = _pano()
    a, b = _Bright("push_pull"), backends.FillBackend("sh")
    blend = backends.BlendBackend([a, b], [3.0, 1.0], keep_lights=False)   # 3/4, 1/4
    out, oa, ob = (m.complete(rgb, normal, mask) for m in (blend, a, b))
    seen, hole = mask > 0.5, mask < 0.5
    for e in completion.DEFAULT_EVS:
        np.testing.assert_array_equal(out[e][seen], oa[e][seen])
        ref = hdr.expose(0.75 * hdr.unexpose(oa[e], e) + 0.25 * hdr.unexpose(ob[e], e), e)
        np.testing.assert_allclose(out[e][hole], ref[hole], atol=2e-6)
        assert out[e].dtype == np.float32 and out[e].shape == rgb.shape
    # the fused hole's radiance is the weighted mean (both fills stay below EV -5's white)
    fused = hdr.fuse_brackets(out)
    want = 0.75 * hdr.fuse_brackets(oa) + 0.25 * hdr.fuse_brackets(ob)
    np.testing.assert_allclose(fused[hole], want[hole], rtol=1e-4, atol=1e-6)
    assert blend.name == "push_pull+sh"


def _colour_check(out, ref_lum, ref_col, mask, skip=None):
    """In the hole of every bracket (but ``skip``): luminance of ``ref_lum``, chromaticity of
    ``ref_col``."""
    from comgs_dr.core.colorspace import LUMA
    hole = (mask < 0.5) & (True if skip is None else ~skip)
    for e in completion.DEFAULT_EVS:
        r_out, r_l, r_c = (hdr.unexpose(np.asarray(x[e], np.float64), e)
                           for x in (out, ref_lum, ref_col))
        ok = (hole & (r_out.max(-1) < 0.9 * 2.0 ** -e) & (r_c @ LUMA > 1e-6)
              & (r_l.max(-1) < 0.9 * 2.0 ** -e) & (r_c.max(-1) < 0.9 * 2.0 ** -e))
        assert ok.sum() > 0.5 * hole.sum()                               # none clipped there
        np.testing.assert_allclose((r_out @ LUMA)[ok], (r_l @ LUMA)[ok], rtol=1e-3, atol=1e-5)
        chroma = lambda r: r[ok] / (r[ok] @ LUMA)[:, None]             # noqa: E731
        np.testing.assert_allclose(chroma(r_out), chroma(r_c), rtol=1e-3, atol=1e-4)


def test_blend_backend_mixes_colour_apart_from_luminance():
    rgb, normal, mask = _pano()
    rgb = rgb * np.array([1.0, 0.7, 0.4])                     # a warm scene: colours differ
    a, b = backends.FillBackend("push_pull"), backends.FillBackend("sh")
    seen, hole = mask > 0.5, mask < 0.5
    oa = a.complete(rgb, normal, mask)
    # the 3:1 mean's luminance in the first's colour
    first = backends.BlendBackend([a, b], [3.0, 1.0], keep_lights=False, colour_weights=(1, 0))
    mean = backends.BlendBackend([a, b], [3.0, 1.0], keep_lights=False)
    out, ref = first.complete(rgb, normal, mask), mean.complete(rgb, normal, mask)
    for e in completion.DEFAULT_EVS:
        np.testing.assert_array_equal(out[e][seen], oa[e][seen])
    _colour_check(out, ref, oa, mask)
    assert not np.allclose(out[0.0][hole], ref[0.0][hole], atol=1e-3)   # it is not the mean
    # outdoors (label colour weights): the first's luminance alone, the ½/½ mean's colour;
    # both members run although the second has luminance weight 0
    mix = backends.BlendBackend([a, b], keep_lights=False, label_weights={"outdoor": (1, 0)},
                                label_colour_weights={"outdoor": (1, 1)})
    half = backends.BlendBackend([a, b], keep_lights=False)
    out = mix.complete(rgb, normal, mask, label="outdoor")
    _colour_check(out, oa, half.complete(rgb, normal, mask, label="outdoor"), mask)
    np.testing.assert_array_equal(mix.complete(rgb, normal, mask, label="indoor")[0.0],
                                  half.complete(rgb, normal, mask, label="indoor")[0.0])
    with pytest.raises(ValueError, match="colour"):
        backends.BlendBackend([a, b], colour_weights=(0, 0))
    with pytest.raises(ValueError, match="colour of label"):
        backends.BlendBackend([a, b], label_colour_weights={"outdoor": (1.0,)})


class _LampInHole(backends.FillBackend):
    """A push-pull fill that puts a white lamp in the hole (8x the white at EV < 0)."""

    def complete(self, rgb, normal, mask, evs=completion.DEFAULT_EVS, label=2):
        out = super().complete(rgb, normal, mask, evs, label)
        rad = hdr.unexpose(out[0.0], 0.0)
        rad[10:12, 14:16] = 8.0
        return {e: hdr.expose(rad, e).astype(np.float32) for e in out}


def test_net_sh_blend_outdoors_keeps_the_nets_luminance_and_lights():
    """Outdoors (the default colour): observed pixels and the net's lamp in the hole are the
    net's in every bracket; elsewhere in the hole the net's luminance, the ½/½ mean's colour."""
    rgb, normal, mask = _pano()
    rgb = rgb * np.array([1.0, 0.7, 0.4])
    net, sh = _LampInHole("push_pull"), backends.FillBackend("sh")
    out = backends.net_sh_blend(net).complete(rgb, normal, mask, label="outdoor")
    on = net.complete(rgb, normal, mask)
    keep = (mask > 0.5) | (on[0.0].max(-1) >= 0.95)
    assert keep[10:12, 14:16].all()
    for e in completion.DEFAULT_EVS:
        np.testing.assert_array_equal(out[e][keep], on[e][keep])
    half = backends.BlendBackend([net, sh], keep_lights=False)
    _colour_check(out, on, half.complete(rgb, normal, mask, label="outdoor"), mask, keep)
    # the fused lamp keeps its power
    np.testing.assert_allclose(hdr.fuse_brackets(out)[10:12, 14:16],
                               hdr.fuse_brackets(on)[10:12, 14:16])


def test_net_sh_blend_colour_choices():
    fill = backends.FillBackend("push_pull")
    d = backends.net_sh_blend(fill)
    np.testing.assert_array_equal(d.colour_weights_for("outdoor"), [0.5, 0.5])
    assert d.colour_weights_for("indoor") is None and d.colour_weights_for("unknown") is None
    assert backends.net_sh_blend(fill, "mean").colour_weights_for("outdoor") is None
    f = backends.net_sh_blend(fill, "first")
    for lab in ("outdoor", "indoor"):
        np.testing.assert_array_equal(f.colour_weights_for(lab), [1.0, 0.0])
    with pytest.raises(ValueError, match="colour"):
        backends.net_sh_blend(fill, "sh")


def test_blend_backend_rejects_bad_weights_and_inputs():
    fill = backends.FillBackend("sh")
    for w in ([1.0], [1.0, -1.0], [0.0, 0.0], [np.nan, 1.0]):
        with pytest.raises(ValueError):
            backends.BlendBackend([fill, fill], w)
    with pytest.raises(ValueError):
        backends.BlendBackend([])
    with pytest.raises(ValueError, match="BlendBackend"):
        backends.BlendBackend([fill]).complete(np.zeros((4, 8, 3)), None, np.ones((4, 9)))
    rgb, mask = np.full((4, 8, 3), 0.5), np.ones((4, 8))
    with pytest.raises(ValueError, match="evs must include 0"):      # keep_lights needs EV 0
        backends.BlendBackend([fill, fill]).complete(rgb, None, mask, evs=(-2.5,))
    out = backends.BlendBackend([fill, fill], keep_lights=False).complete(rgb, None, mask,
                                                                         evs=(-2.5,))
    assert list(out) == [-2.5]


def test_blend_backend_keeps_the_first_backends_lights_in_the_hole():
    rgb, normal, mask = _pano()

    class _Lamp(backends.FillBackend):       # puts a clipped lamp into the hole
        def complete(self, rgb, normal, mask, evs=completion.DEFAULT_EVS, label=2):
            out = super().complete(rgb, normal, mask, evs, label)
            rad = hdr.unexpose(out[0.0], 0.0)
            rad[10:12, 14:16] = 20.0
            return {e: hdr.expose(rad, e).astype(np.float32) for e in out}

    a, b = _Lamp("push_pull"), backends.FillBackend("sh")
    oa = a.complete(rgb, normal, mask)
    kept = backends.BlendBackend([a, b]).complete(rgb, normal, mask)
    halved = backends.BlendBackend([a, b], keep_lights=False).complete(rgb, normal, mask)
    lamp = np.zeros(mask.shape, bool)
    lamp[10:12, 14:16] = True
    for e in completion.DEFAULT_EVS:
        np.testing.assert_array_equal(kept[e][lamp], oa[e][lamp])
    f_kept, f_half = hdr.fuse_brackets(kept), hdr.fuse_brackets(halved)
    np.testing.assert_allclose(f_kept[lamp], 20.0, rtol=1e-3)
    assert (f_half[lamp] < 11.0).all()                                   # ½ lamp + ½ SH
    rest = (mask < 0.5) & ~lamp
    np.testing.assert_array_equal(f_kept[rest], f_half[rest])


def test_blend_backend_label_weights_run_only_the_members_needed():
    """``label_weights`` replaces the weights for that label; a member of weight 0 is not
    run, and the first member alone gives its own brackets."""
    calls = []

    class Count(backends.FillBackend):
        def complete(self, *a, **k):
            calls.append(self.kind)
            return super().complete(*a, **k)

    a, b = Count("mean"), Count("sh")
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.1, 0.9, (8, 16, 3)).astype(np.float32)
    mask = np.zeros((8, 16), np.float32)
    mask[:, :9] = 1
    blend = backends.BlendBackend([a, b], label_weights={"outdoor": (1.0, 0.0)})
    np.testing.assert_array_equal(blend.weights_for("outdoor"), [1.0, 0.0])
    np.testing.assert_array_equal(blend.weights_for(0), [1.0, 0.0])       # outdoor
    np.testing.assert_array_equal(blend.weights_for(1), [0.5, 0.5])       # indoor
    out = blend.complete(rgb, None, mask, label="outdoor")
    assert calls == ["mean"]
    ref = a.complete(rgb, None, mask, label="outdoor")
    for e in ref:
        np.testing.assert_array_equal(out[e], ref[e])
    calls.clear()
    mixed = blend.complete(rgb, None, mask, label="indoor")
    assert calls == ["mean", "sh"]
    assert not np.array_equal(mixed[0.0], out[0.0])
    with pytest.raises(ValueError, match="label"):
        backends.BlendBackend([a, b], label_weights={"outdoor": (0.0, 0.0)})
    with pytest.raises(ValueError, match="unknown label"):
        backends.BlendBackend([a, b], label_weights={"space": (1.0, 0.0)})
    d = backends.default_backend()
    np.testing.assert_array_equal(d.weights_for("outdoor"), [1.0, 0.0])
    np.testing.assert_array_equal(d.weights_for("indoor"), [0.5, 0.5])


def test_diffusers_from_dir_rejects_a_bad_embeddings_file(tmp_path):
    """ev_embeddings.pt goes through lighting.torch_io.load_torch_file: an unreadable file or
    one without xi_b / xi_d is a ValueError naming it (before any model is loaded)."""
    emb = tmp_path / backends.DiffusersBackend.EMBEDDINGS_FILE
    emb.write_bytes(b"not torch")
    with pytest.raises(ValueError, match="ev_embeddings.pt: not a readable DiffusersBackend"):
        backends.DiffusersBackend.from_dir(tmp_path)
    torch.save({"xi_b": torch.zeros(2)}, emb)
    with pytest.raises(ValueError, match="must hold a dict with 'xi_b' and 'xi_d'"):
        backends.DiffusersBackend.from_dir(tmp_path)
