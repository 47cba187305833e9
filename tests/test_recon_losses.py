"""Step-1 reconstruction losses (comgs_dr.train.losses): values vs a torch reference
of the 3DGS SSIM, gradients (autograd reference, central differences), depth→normal
on analytic surfaces, degenerate inputs and shape errors. Images ≤ 32×32."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from comgs_dr.core import cameras
from comgs_dr.core.hostarray import to_jit
from comgs_dr.surfels.scene import gbuffer_scene
from comgs_dr.train import losses as L

torch = pytest.importorskip("torch")
F = torch.nn.functional


# ------------------------------------------------------------------ references
def _torch_window(window=11, sigma=1.5, channels=3):
    """3DGS ``create_window``: outer product of the normalised 1-D Gaussian."""
    g = torch.tensor([math.exp(-(x - window // 2) ** 2 / float(2 * sigma ** 2)) for x in range(window)],
                     dtype=torch.float64)
    g = (g / g.sum()).unsqueeze(1)
    w2 = g.mm(g.t()).unsqueeze(0).unsqueeze(0)
    return w2.expand(channels, 1, window, window).contiguous()


def ssim_torch(img1, img2, window=11, sigma=1.5):
    """3DGS ``utils/loss_utils.py::_ssim`` (size_average) on [H, W, C] float64 tensors."""
    C = img1.shape[2]
    a, b = img1.permute(2, 0, 1)[None], img2.permute(2, 0, 1)[None]
    w = _torch_window(window, sigma, C)
    conv = lambda x: F.conv2d(x, w, padding=window // 2, groups=C)  # noqa: E731
    mu1, mu2 = conv(a), conv(b)
    mu1_sq, mu2_sq, mu1_mu2 = mu1.pow(2), mu2.pow(2), mu1 * mu2
    sigma1_sq = conv(a * a) - mu1_sq
    sigma2_sq = conv(b * b) - mu2_sq
    sigma12 = conv(a * b) - mu1_mu2
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    m = ((2 * mu1_mu2 + C1) * (2 * sigma12 + C2)) / ((mu1_sq + mu2_sq + C1) * (sigma1_sq + sigma2_sq + C2))
    return m.mean()


def _t(a):
    return to_jit(mi.TensorXf, a)


def _f(x) -> float:
    return float(np.array(x).reshape(-1)[0])


def _structured(H, W, rng):
    """Smooth gradients + checkerboard + edges + a little noise, in [0, 1]."""
    y, x = np.mgrid[0:H, 0:W] / max(H, W)
    r = 0.5 + 0.4 * np.sin(6 * x) * np.cos(4 * y)
    g = ((np.floor(x * 8) + np.floor(y * 8)) % 2) * 0.8 + 0.1
    b = (x + y > 0.8).astype(float) * 0.7 + 0.15
    img = np.stack([r, g, b], -1) + rng.normal(0, 0.02, (H, W, 3))
    return np.clip(img, 0, 1)


IMAGES = {
    "random": lambda rng: (rng.random((32, 32, 3)), rng.random((32, 32, 3))),
    "structured": lambda rng: (_structured(32, 32, rng), np.clip(_structured(32, 32, rng)
                                                                 + rng.normal(0, 0.1, (32, 32, 3)), 0, 1)),
    "non_square": lambda rng: (rng.random((17, 29, 3)), rng.random((17, 29, 3))),
    "one_channel": lambda rng: (rng.random((20, 24, 1)), rng.random((20, 24, 1))),
    "smaller_than_window": lambda rng: (rng.random((5, 4, 3)), rng.random((5, 4, 3))),
    "structured_vs_shifted": lambda rng: (_structured(24, 32, rng), np.roll(_structured(24, 32, rng), 2, 1)),
}


# ------------------------------------------------------------------ SSIM / L1 values
@pytest.mark.parametrize("kind", list(IMAGES))
def test_ssim_matches_3dgs_torch_reference(kind, rng):
    a, b = IMAGES[kind](rng)
    a, b = a.astype(np.float32), b.astype(np.float32)
    ref = ssim_torch(torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64)).item()
    got = _f(L.ssim(_t(a), _t(b)))
    # float32 statistics (σ² = E[x²] − μ² cancels): ~1e-6 absolute on the mean
    assert abs(got - ref) < 2e-5, (got, ref)
    ref_map = _ssim_map_torch(a, b)
    got_map = np.array(L.ssim_map(_t(a), _t(b)))
    np.testing.assert_allclose(got_map, ref_map, atol=2e-4)


def _ssim_map_torch(a, b):
    C = a.shape[2]
    ta, tb = (torch.tensor(x, dtype=torch.float64).permute(2, 0, 1)[None] for x in (a, b))
    w = _torch_window(11, 1.5, C)
    conv = lambda x: F.conv2d(x, w, padding=5, groups=C)  # noqa: E731
    mu1, mu2 = conv(ta), conv(tb)
    s11, s22, s12 = conv(ta * ta) - mu1 ** 2, conv(tb * tb) - mu2 ** 2, conv(ta * tb) - mu1 * mu2
    m = ((2 * mu1 * mu2 + 1e-4) * (2 * s12 + 9e-4)) / ((mu1 ** 2 + mu2 ** 2 + 1e-4) * (s11 + s22 + 9e-4))
    return m[0].permute(1, 2, 0).numpy()


def test_blur_matches_conv2d(rng):
    a = rng.random((13, 18, 2)).astype(np.float32)
    ref = F.conv2d(torch.tensor(a, dtype=torch.float64).permute(2, 0, 1)[None], _torch_window(11, 1.5, 2),
                   padding=5, groups=2)[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(np.array(L.blur(_t(a))), ref, atol=1e-6)
    ref7 = F.conv2d(torch.tensor(a, dtype=torch.float64).permute(2, 0, 1)[None], _torch_window(7, 2.0, 2),
                    padding=3, groups=2)[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(np.array(L.blur(_t(a), 7, 2.0)), ref7, atol=1e-6)


@pytest.mark.parametrize("img", ["random", "constant", "zeros", "ones"])
def test_ssim_identical_is_one(img, rng):
    a = {"random": rng.random((16, 16, 3)), "constant": np.full((16, 16, 3), 0.37),
         "zeros": np.zeros((16, 16, 3)), "ones": np.ones((16, 16, 3))}[img]
    assert abs(_f(L.ssim(_t(a), _t(a))) - 1.0) < 1e-6
    assert _f(L.l1(_t(a), _t(a))) == 0.0
    assert abs(_f(L.rgb_loss(_t(a), _t(a)))) < 1e-6


def test_l1_and_masked_l1(rng):
    a, b = rng.random((12, 10, 3)), rng.random((12, 10, 3))
    m = (rng.random((12, 10)) > 0.4).astype(np.float32)
    assert abs(_f(L.l1(_t(a), _t(b))) - np.abs(a - b).mean()) < 1e-6
    ref = (np.abs(a - b) * m[..., None]).sum() / (3 * m.sum())
    assert abs(_f(L.l1(_t(a), _t(b), _t(m))) - ref) < 1e-6
    assert abs(_f(L.l1(_t(a), _t(b), _t(m[..., None]))) - ref) < 1e-6
    assert _f(L.l1(_t(a), _t(b), _t(np.zeros((12, 10))))) == 0.0


def test_rgb_loss_is_l1_plus_02_dssim(rng):
    a, b = _structured(20, 20, rng), rng.random((20, 20, 3))
    ta, tb = torch.tensor(a), torch.tensor(b)
    ref = (ta - tb).abs().mean().item() + 0.2 * (1 - ssim_torch(ta, tb).item())
    assert abs(_f(L.rgb_loss(_t(a), _t(b))) - ref) < 2e-5
    ref5 = (ta - tb).abs().mean().item() + 0.5 * (1 - ssim_torch(ta, tb).item())
    assert abs(_f(L.rgb_loss(_t(a), _t(b), lambda_ssim=0.5)) - ref5) < 2e-5


# ------------------------------------------------------------------ SSIM / L1 gradients
def _grad(fn, a_np, *rest):
    a = _t(a_np)
    dr.enable_grad(a)
    y = fn(a, *rest)
    dr.backward(y)
    return _f(y), np.array(dr.grad(a))


@pytest.mark.parametrize("kind", ["random", "structured", "non_square"])
def test_ssim_gradient_matches_torch_autograd(kind, rng):
    a, b = IMAGES[kind](rng)
    _, g = _grad(lambda x: L.ssim(x, _t(b)), a)
    ta = torch.tensor(a.astype(np.float32), dtype=torch.float64, requires_grad=True)
    ssim_torch(ta, torch.tensor(b.astype(np.float32), dtype=torch.float64)).backward()
    ref = ta.grad.numpy()
    # float32 forward/adjoint: errors ~1e-6 of the largest entry
    np.testing.assert_allclose(g, ref, atol=1e-4 * np.abs(ref).max())


def test_rgb_loss_gradient_matches_torch_autograd(rng):
    a, b = _structured(24, 24, rng), rng.random((24, 24, 3))
    b = np.where(np.abs(a - b) < 1e-3, b + 0.01, b)          # avoid |a − b| kinks
    _, g = _grad(lambda x: L.rgb_loss(x, _t(b)), a)
    ta = torch.tensor(a.astype(np.float32), dtype=torch.float64, requires_grad=True)
    tb = torch.tensor(b.astype(np.float32), dtype=torch.float64)
    ((ta - tb).abs().mean() + 0.2 * (1 - ssim_torch(ta, tb))).backward()
    np.testing.assert_allclose(g, ta.grad.numpy(), atol=1e-4 * np.abs(ta.grad.numpy()).max())


def _directional(fn, x0, v, h):
    """Central difference (f(x + hv) − f(x − hv)) / 2h evaluated in float32."""
    return (_f(fn(_t(x0 + h * v))) - _f(fn(_t(x0 - h * v)))) / (2 * h)


@pytest.mark.parametrize("loss", ["ssim", "l1", "rgb"])
def test_rgb_gradients_by_central_differences(loss, rng):
    """Directional derivatives ⟨∇f, v⟩, all pixels moved at once. float32: f ≈ 0.1–0.5
    carries ~1e-7 absolute rounding, i.e. ~1e-4 on the quotient at h = 1e-3. Along
    v = sign(∇f)·u (no cancellation, ⟨∇f, v⟩ ≈ 0.1) tolerance 1% relative; along a random
    Gaussian v (⟨∇f, v⟩ ≈ 3e-3 from cancellation) h = 1e-2 (rounding ~1e-5; O(h²)
    truncation ≲ 1e-4 relative) and tolerance 2% relative + 2e-5."""
    a = _structured(32, 32, rng)
    b = np.clip(a + rng.choice([-1, 1], a.shape) * rng.uniform(0.05, 0.3, a.shape), 0, 1)
    b = np.where(np.abs(a - b) < 0.05, a + 0.1, b)          # |a − b| ≥ 0.05: no L1 kink within h
    fn = {"ssim": lambda x: L.ssim(x, _t(b)), "l1": lambda x: L.l1(x, _t(b)),
          "rgb": lambda x: L.rgb_loss(x, _t(b))}[loss]
    _, g = _grad(fn, a)
    v = np.sign(g) * rng.uniform(0.5, 1.0, a.shape)
    fd, an = _directional(fn, a, v, 1e-3), float((g * v).sum())
    assert an > 0.02 and abs(fd - an) <= 1e-2 * an, (fd, an)
    for _ in range(2):
        v = rng.normal(size=a.shape)
        fd = _directional(fn, a, v, 1e-2 if loss != "l1" else 1e-3)
        an = float((g * v).sum())
        assert abs(fd - an) <= 2e-2 * abs(an) + 2e-5, (fd, an)


def test_blur_adjoint_forward_mode(rng):
    """Forward-mode tangent of the blur op equals the blur of the tangent (linear op)."""
    a = _t(rng.random((9, 14, 3)))
    v = rng.normal(size=(9, 14, 3)).astype(np.float32)
    dr.enable_grad(a)
    y = L.blur(a)
    dr.set_grad(a, _t(v))
    dr.forward_to(y)
    np.testing.assert_allclose(np.array(dr.grad(y)), np.array(L.blur(_t(v))), atol=1e-6)


# ------------------------------------------------------------------ cameras
def test_camera_rays_through_pixel_centres_with_principal_point():
    s = cameras.perspective([3, -2, 2], res=(12, 8))
    s["principal_point_offset_x"] = 0.15
    s["principal_point_offset_y"] = -0.1
    sensor = mi.load_dict(s)
    d, o = cameras.camera_rays(sensor)
    assert tuple(d.shape) == (8, 12, 3) and tuple(o.shape) == (8, 12, 3)
    dn, on = np.array(d), np.array(o)
    np.testing.assert_allclose(np.linalg.norm(dn, axis=-1), 1, atol=1e-6)
    # Mitsuba's perspective rays start on the near-clip plane: o = o_cam + t_near·d, and the
    # G-buffer measures depth from there — hence per-pixel origins
    t_near = ((on - [3, -2, 2]) * dn).sum(-1)
    np.testing.assert_allclose(on, [3, -2, 2] + t_near[..., None] * dn, atol=1e-6)
    assert np.all(t_near >= 0.01 - 1e-6) and np.all(t_near < 0.02)
    p = (on + 2.5 * dn).reshape(-1, 3)
    it = dr.zeros(mi.Interaction3f, p.shape[0])
    it.p = to_jit(mi.Point3f, p.T)
    ds, _ = sensor.sample_direction(it, mi.Point2f(0.5))
    uv = np.array(ds.uv).T.reshape(8, 12, 2)
    yy, xx = np.mgrid[0:8, 0:12]
    np.testing.assert_allclose(uv, np.stack([xx + 0.5, yy + 0.5], -1), atol=1e-3)
    d2, _ = cameras.camera_rays(s, 12, 8)                                       # dict + explicit size
    np.testing.assert_allclose(np.array(d2), dn, atol=1e-6)


# ------------------------------------------------------------------ depth → normal
def _angle_deg(a, b):
    """Angle in degrees, in float64 via atan2 (arccos of a float32 dot is quantised to ~0.02°)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def _plane_setup(ppo=0.0, res=(32, 24)):
    s = cameras.perspective([2.0, -2.5, 2.0], target=[0.1, 0.2, 0.0], res=res, fov=50)
    s["principal_point_offset_x"] = ppo
    d, o = cameras.camera_rays(s)
    n = np.array([0.2, -0.1, 1.0])
    n /= np.linalg.norm(n)
    p0 = np.array([0.0, 0.0, -0.1])
    dn, on = np.array(d, dtype=np.float64), np.array(o, dtype=np.float64)
    t = ((p0 - on) @ n) / (dn @ n)                                         # [H, W] along unit rays
    assert np.all(t > 0)
    return d, o, t, n


@pytest.mark.parametrize("ppo", [0.0, 0.2])
def test_depth_to_normal_plane(ppo):
    d, o, t, n = _plane_setup(ppo)
    H, W = t.shape
    nd, valid = L.depth_to_normal(_t(t[..., None]), d, o, return_valid=True)
    nd = np.array(nd)
    valid = np.array(valid).reshape(H, W)
    inner = np.zeros((H, W), bool)
    inner[1:-1, 1:-1] = True
    assert np.array_equal(valid, inner)
    assert np.all(nd[~inner] == 0)
    # camera is above the plane: the facing normal is +n. float32 points at distance ~4
    # with ~0.1 spacing between neighbours: angular error ~1e-5 rad; bound 0.01°.
    assert _angle_deg(nd[inner], np.broadcast_to(n, nd[inner].shape)).max() < 0.01
    assert np.all((nd[inner] * np.array(d)[inner]).sum(-1) < 0)
    # a single origin 3-vector (camera centre, depth measured from it) and an [H, W] depth
    cam = np.array([2.0, -2.5, 2.0])
    t_cam = t + ((np.array(o, dtype=np.float64) - cam) * np.array(d, dtype=np.float64)).sum(-1)
    nd2 = np.array(L.depth_to_normal(_t(t_cam), d, cam))
    np.testing.assert_allclose(nd2, nd, atol=1e-5)


def _sphere_setup(res=32, center=(0.2, 0.1, -0.1), R=1.0):
    s = cameras.perspective([0.4, -2.6, 0.7], target=[0.0, 0.0, 0.0], res=res, fov=50)
    d, o = cameras.camera_rays(s)
    dn, on = np.array(d, dtype=np.float64), np.array(o, dtype=np.float64)
    oc = on - np.asarray(center)
    bq = (oc * dn).sum(-1)
    disc = bq ** 2 - ((oc * oc).sum(-1) - R * R)
    hit = disc > 0
    t = np.where(hit, -bq - np.sqrt(np.maximum(disc, 0)), 0.0)
    x = on + t[..., None] * dn
    n_true = (x - np.asarray(center)) / R
    return d, o, t, hit, n_true, dn


def test_depth_to_normal_sphere():
    d, o, t, hit, n_true, dn = _sphere_setup()
    H, W = t.shape
    weight = hit.astype(np.float32)
    nd, valid = L.depth_to_normal(_t(t), d, o, weight=_t(weight), return_valid=True)
    nd, valid = np.array(nd), np.array(valid).reshape(H, W)
    # valid = interior pixels whose 4-neighbourhood hits the sphere
    nbr = np.zeros_like(hit)
    nbr[1:-1, 1:-1] = hit[1:-1, 1:-1] & hit[2:, 1:-1] & hit[:-2, 1:-1] & hit[1:-1, 2:] & hit[1:-1, :-2]
    assert np.array_equal(valid, nbr) and valid.sum() > 150
    assert np.all(nd[~valid] == 0)
    # implementation: same as float64 central differences of the analytic points (0.01°)
    X = np.array(o, np.float64) + t[..., None] * dn
    c = np.zeros_like(X)
    c[1:-1, 1:-1] = np.cross(X[1:-1, 2:] - X[1:-1, :-2], X[2:, 1:-1] - X[:-2, 1:-1])
    c *= -np.sign((c * dn).sum(-1, keepdims=True))
    assert _angle_deg(nd[valid], c[valid]).max() < 0.01
    # discretisation vs the true normal: central differences over a footprint h ≈ 0.05 R
    # err O(h²) ≈ 0.1° facing the camera, growing as 1/cos θ³ towards the silhouette
    # (measured max 0.47° for cos θ > 0.6, 4.6° over all valid pixels); bounds 1°, 0.3°
    facing = -(n_true * dn).sum(-1)                                        # cos θ
    ang = _angle_deg(nd[valid], n_true[valid])
    interior = facing[valid] > 0.6
    assert interior.sum() > 200
    assert ang[interior].max() < 1.0, ang[interior].max()
    assert np.median(ang) < 0.3
    assert np.all((nd[valid] * dn[valid]).sum(-1) < 0)


# ------------------------------------------------------------------ d2n loss
def _d2n_inputs(rng):
    d, o, t, n = _plane_setup(res=(20, 16))
    H, W = t.shape
    depth = t * (1 + 0.01 * rng.normal(size=t.shape))                     # bumpy plane
    N = n + 0.2 * rng.normal(size=(H, W, 3))
    N *= rng.uniform(0.7, 1.0, (H, W, 1)) / np.linalg.norm(N, axis=-1, keepdims=True)
    Wt = rng.uniform(0.6, 1.0, (H, W, 1))
    Wt[3, 4] = 0.2                                                         # below min_weight
    return d, o, depth[..., None], N, Wt


def test_d2n_loss_value_and_normal_gradient(rng):
    d, o, depth, N, Wt = _d2n_inputs(rng)
    nd, valid = L.depth_to_normal(_t(depth), d, o, weight=_t(Wt), return_valid=True)
    nd, valid = np.array(nd), np.array(valid).reshape(Wt.shape[:2])
    assert not valid[3, 4] and not valid[2, 4] and valid[6, 6]
    ref = (Wt[..., 0] * (1 - (N * nd).sum(-1)))[valid].mean()
    tN = _t(N)
    dr.enable_grad(tN)
    loss = L.d2n_loss(tN, _t(depth), _t(Wt), d, o)
    dr.backward(loss)
    assert abs(_f(loss) - ref) < 1e-5
    gref = np.where(valid[..., None], -Wt * nd / valid.sum(), 0)        # linear in N: exact
    np.testing.assert_allclose(np.array(dr.grad(tN)), gref, atol=1e-7)


@pytest.mark.parametrize("detach", [False, True])
def test_d2n_loss_depth_gradient_central_differences(detach, rng):
    """⟨∂L/∂D, v⟩ vs (L(D + hv) − L(D − hv)) / 2h with h = 1e-3 (depth ≈ 3, neighbour
    spacing ≈ 0.1): float32 points carry ~3e-7 absolute error → ~1e-5 relative noise
    on the quotient; O(h²) truncation ~1e-4. Tolerance 2% relative."""
    d, o, depth, N, Wt = _d2n_inputs(rng)
    fn = lambda D: L.d2n_loss(_t(N), D, _t(Wt), d, o, detach_depth_normal=detach)  # noqa: E731
    tD = _t(depth)
    dr.enable_grad(tD)
    dr.backward(fn(tD), flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    g = np.array(dr.grad(tD))
    assert np.all(np.isfinite(g))
    if detach:
        assert np.all(g == 0)
        return
    assert np.abs(g).max() > 0
    for _ in range(2):
        v = rng.normal(size=depth.shape) * depth
        fd = _directional(fn, depth, v, 1e-3 / depth.mean())
        an = float((g * v).sum())
        assert abs(fd - an) <= 2e-2 * abs(an) + 1e-6, (fd, an)


def test_d2n_loss_zero_on_consistent_plane():
    d, o, t, n = _plane_setup(res=(16, 16))
    N = np.broadcast_to(n, t.shape + (3,)).copy()
    loss = L.d2n_loss(_t(N), _t(t), _t(np.ones_like(t)), d, o)
    assert abs(_f(loss)) < 1e-6


# ------------------------------------------------------------------ mask loss
def test_mask_loss_value_and_gradient(rng):
    Wt = rng.uniform(0.05, 0.95, (16, 12, 1))
    K = (rng.random((16, 12)) > 0.5).astype(np.float32)
    K[0, :3] = 0.3                                                         # soft mask values
    Wf = Wt.astype(np.float32).astype(np.float64)
    ref = np.mean(-K[..., None] * np.log(Wf) - (1 - K[..., None]) * np.log(1 - Wf))
    tw = _t(Wt)
    dr.enable_grad(tw)
    loss = L.mask_loss(tw, _t(K))
    dr.backward(loss)
    assert abs(_f(loss) - ref) < 1e-5 * ref
    gref = (-K[..., None] / Wf + (1 - K[..., None]) / (1 - Wf)) / K.size
    np.testing.assert_allclose(np.array(dr.grad(tw)), gref, rtol=1e-4, atol=1e-9)
    # central differences: loss ≈ 0.7, h = 1e-3 on W ∈ [0.05, 0.95]: rounding ~1e-4
    # relative, truncation h²·f'''/6 ≲ 1e-3 relative; tolerance 1%
    fn = lambda w: L.mask_loss(w, _t(K))  # noqa: E731
    v = rng.normal(size=Wt.shape)
    fd, an = _directional(fn, Wt, v, 1e-3), float((np.array(dr.grad(tw)) * v).sum())
    assert abs(fd - an) <= 1e-2 * abs(an), (fd, an)


def test_binary_loss_value_gradient_and_extremes(rng):
    Wt = rng.uniform(0.05, 0.95, (16, 12, 1))
    Wf = Wt.astype(np.float32).astype(np.float64)
    ref = np.mean(-Wf * np.log(Wf) - (1 - Wf) * np.log(1 - Wf))
    tw = _t(Wt)
    dr.enable_grad(tw)
    loss = L.binary_loss(tw)
    dr.backward(loss)
    assert abs(_f(loss) - ref) < 1e-5 * ref
    np.testing.assert_allclose(np.array(dr.grad(tw)), np.log((1 - Wf) / Wf) / Wf.size,
                               rtol=1e-3, atol=1e-8)
    v = rng.normal(size=Wt.shape)
    fd, an = _directional(L.binary_loss, Wt, v, 1e-3), float((np.array(dr.grad(tw)) * v).sum())
    assert abs(fd - an) <= 1e-2 * abs(an), (fd, an)
    y, (g,) = _finite_grad(L.binary_loss, np.array([[0.0], [1.0], [0.5]]).reshape(3, 1, 1))
    assert np.isfinite(y) and np.all(np.isfinite(g)) and abs(y - np.log(2) / 3) < 1e-4


# ------------------------------------------------------------------ extreme inputs
def _finite_grad(fn, *arrays):
    ts = [_t(a) for a in arrays]
    for t in ts:
        dr.enable_grad(t)
    y = fn(*ts)
    dr.backward(y)
    grads = [np.array(dr.grad(t)) for t in ts]
    assert np.isfinite(_f(y)), _f(y)
    for g in grads:
        assert np.all(np.isfinite(g))
    return _f(y), grads


def test_extreme_mask_weights():
    Wt = np.zeros((8, 8, 1))
    Wt[:4] = 1.0
    K = np.zeros((8, 8))
    K[:4] = 1.0
    y, (gw, _) = _finite_grad(L.mask_loss, Wt, K)
    assert 0 <= y < 1e-4                                                   # −log(1 − 1e-5)
    assert np.all(gw == 0)                                                 # clamped: no gradient
    y, (gw, _) = _finite_grad(L.mask_loss, Wt, 1 - K)                      # maximally wrong
    assert abs(y - (-math.log(1e-5))) < 1e-2 and np.all(gw == 0)


@pytest.mark.parametrize("case", ["depth_zero", "weight_zero", "depth_nan", "depth_inf", "weight_one_flat"])
def test_extreme_d2n_inputs(case, rng):
    d, o, t, n = _plane_setup(res=(12, 10))
    H, W = t.shape
    N = np.broadcast_to(n, (H, W, 3)).copy()
    depth, Wt = t.copy(), np.ones((H, W))
    if case == "depth_zero":
        depth[:] = 0
    elif case == "weight_zero":
        Wt[:] = 0
    elif case == "depth_nan":
        depth[2:5, 3:6] = np.nan
    elif case == "depth_inf":
        depth[4, :] = np.inf
    y, grads = _finite_grad(lambda nn, dd, ww: L.d2n_loss(nn, dd, ww, d, o), N, depth, Wt)
    if case in ("depth_zero", "weight_zero"):
        assert y == 0 and all(np.all(g == 0) for g in grads)
    else:
        assert abs(y) < 1e-5
    nd = np.array(L.depth_to_normal(_t(depth), d, o, weight=_t(Wt)))
    assert np.all(np.isfinite(nd))


@pytest.mark.parametrize("pair", ["const_same", "const_diff", "zeros_ones", "tiny_values"])
def test_extreme_rgb_inputs(pair, rng):
    a, b = {"const_same": (np.full((10, 10, 3), 0.5), np.full((10, 10, 3), 0.5)),
            "const_diff": (np.full((10, 10, 3), 0.2), np.full((10, 10, 3), 0.9)),
            "zeros_ones": (np.zeros((10, 10, 3)), np.ones((10, 10, 3))),
            "tiny_values": (np.full((10, 10, 3), 1e-30), rng.random((10, 10, 3)) * 1e-20)}[pair]
    y, grads = _finite_grad(L.rgb_loss, a, b)
    ref = np.abs(a - b).mean() + 0.2 * (1 - ssim_torch(torch.tensor(a), torch.tensor(b)).item())
    assert abs(y - ref) < 1e-5
    _finite_grad(L.ssim, a, b)


# ------------------------------------------------------------------ shape errors
def test_shape_mismatches_raise_value_error():
    a3, b3 = _t(np.zeros((8, 8, 3))), _t(np.zeros((8, 7, 3)))
    d, o = cameras.camera_rays(cameras.perspective([0, -3, 0], res=8))
    one = _t(np.ones((8, 8, 1)))
    cases = [
        (lambda: L.l1(a3, b3), "same shape"),
        (lambda: L.ssim(a3, _t(np.zeros((8, 8, 1)))), "same shape"),
        (lambda: L.rgb_loss(a3, b3), "same shape"),
        (lambda: L.l1(a3, a3, mask=_t(np.ones((8, 7)))), "same shape"),
        (lambda: L.ssim(_t(np.zeros((2, 8, 8, 3))), _t(np.zeros((2, 8, 8, 3)))), "[H, W, C]"),
        (lambda: L.mask_loss(one, _t(np.ones((7, 8)))), "same shape"),
        (lambda: L.mask_loss(a3, one), "channel"),
        (lambda: L.depth_to_normal(a3, d, o), "channel"),
        (lambda: L.depth_to_normal(_t(np.ones((8, 9))), d, o), "same shape"),
        (lambda: L.depth_to_normal(one, d, [0, 1]), "3-vector"),
        (lambda: L.d2n_loss(_t(np.zeros((8, 8, 2))), one, one, d, o), "channel"),
        (lambda: L.d2n_loss(a3, one, _t(np.ones((6, 8))), d, o), "same shape"),
        (lambda: L.ssim(a3, a3, window=4), "odd"),
        (lambda: cameras.camera_rays(cameras.perspective([0, -3, 0], res=8), 8), "both"),
    ]
    for fn, msg in cases:
        with pytest.raises(ValueError, match=msg.replace("[", r"\[").replace("]", r"\]")):
            fn()


# ------------------------------------------------------------------ Step1Loss
def test_step1_loss_total_parts_and_schedule(rng):
    d, o, t, n = _plane_setup(res=(16, 12))
    H, W = t.shape
    buf = {"color": _t(rng.random((H, W, 3))), "weight": _t(rng.uniform(0.6, 1, (H, W, 1))),
           "depth_unbiased": _t(t[..., None] * 1.001),
           "normal": _t(np.broadcast_to(0.9 * (n + [0.1, 0, 0]) / np.linalg.norm(n + [0.1, 0, 0]),
                                             (H, W, 3)).copy())}
    gt, K = rng.random((H, W, 3)), (rng.random((H, W)) > 0.5)
    cfg = L.Step1Loss(lambda_d2n=0.05)
    for k in ("color", "weight", "normal", "depth_unbiased"):
        dr.enable_grad(buf[k])
    total, p = cfg(buf, _t(gt), mask=_t(K.astype(np.float32)), rays=(d, o), iteration=5000)
    assert set(p) == {"l1", "ssim", "rgb", "d2n", "mask", "total"}
    assert all(isinstance(v, float) for v in p.values())
    assert p["d2n"] > 0 and p["mask"] > 0
    assert abs(p["rgb"] - (p["l1"] + 0.2 * (1 - p["ssim"]))) < 1e-6
    assert abs(p["total"] - (p["rgb"] + 0.05 * p["d2n"] + 0.05 * p["mask"])) < 1e-6
    assert abs(p["mask"] - _f(L.mask_loss(buf["weight"], _t(K.astype(np.float32))))) < 1e-6
    dr.backward(total)
    for k in ("color", "weight", "normal", "depth_unbiased"):
        g = np.array(dr.grad(buf[k]))
        assert np.all(np.isfinite(g)) and np.abs(g).max() > 0, k
    # before d2n_from_iteration: no d2n term, rays not needed; no mask: no mask term
    _, p0 = cfg({"color": buf["color"]}, _t(gt), iteration=0)
    assert p0["d2n"] == 0 and p0["mask"] == 0 and abs(p0["total"] - p["rgb"]) < 1e-6
    with pytest.raises(ValueError, match="rays"):
        cfg(buf, _t(gt), iteration=cfg.d2n_from_iteration)
    with pytest.raises(ValueError, match="depth_unbiased"):
        cfg({"color": buf["color"], "normal": buf["normal"], "weight": buf["weight"]}, _t(gt),
            rays=(d, o), iteration=10 ** 6)


def test_step1_loss_defaults_are_the_trainers():
    """The loss the trainer uses is RadianceConfig.loss(); the bare defaults agree with it."""
    from comgs_dr.stages.reconstruct import RadianceConfig
    obj, scene = RadianceConfig().loss(), RadianceConfig.from_preset("scene").loss()
    assert obj == L.Step1Loss()
    assert scene.lambda_mask == 0 and scene.lambda_d2n == obj.lambda_d2n
    c = RadianceConfig(lambda_d2n=0.05, d2n_from=600, lambda_ssim=0.3).loss()
    assert (c.lambda_d2n, c.d2n_from_iteration, c.lambda_ssim) == (0.05, 600, 0.3)
    assert not c.d2n_active(599) and c.d2n_active(600)


# ------------------------------------------------------------------ with the renderer
def test_d2n_on_rendered_surfel_plane():
    """G-buffer conventions end to end: a dense planar surfel layer (z = 0, identity
    rotations), rendered 16×16; where W ≈ 1 the rendered normal and the normal of the
    rendered unbiased depth agree (depth along the unit ray, rays = camera_rays)."""
    from comgs_dr.surfels import SurfelParams
    g = np.linspace(-1.5, 1.5, 31)
    X, Y = np.meshgrid(g, g)
    n = X.size
    params = SurfelParams.from_numpy(
        means=np.stack([X.ravel(), Y.ravel(), np.zeros(n)], 1), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
        log_scales=np.full((n, 2), np.log(0.1)), opacity_logit=np.full(n, 4.0),
        sh=np.full((n, 1, 3), 0.3))
    sensor = cameras.perspective([0.8, -1.6, 2.0], target=[0, 0, 0], res=16, fov=40)
    scene = gbuffer_scene(params, sensor, max_hits=16,
                                  targets="color,weight,depth_unbiased,normal")
    bufs = scene.integrator().split(mi.render(scene))
    d, o = cameras.camera_rays(scene.sensors()[0])
    nd, valid = L.depth_to_normal(bufs["depth_unbiased"], d, o, weight=bufs["weight"],
                                  min_weight=0.9, return_valid=True)
    nd = np.array(nd)[np.array(valid).reshape(16, 16)]
    assert len(nd) > 100
    # the surfels' depth jitter (coplanar tie-breaking) is ≪ the pixel footprint
    # (measured 3e-4°)
    assert _angle_deg(nd, np.broadcast_to([0, 0, 1.0], nd.shape)).max() < 0.05
    # depth is measured from Mitsuba's ray origin (near-clip plane), as camera_rays returns
    m = np.array(valid).reshape(16, 16)
    dn, on = np.array(d, np.float64), np.array(o, np.float64)
    t_plane = -on[..., 2] / dn[..., 2]
    np.testing.assert_allclose(np.array(bufs["depth_unbiased"])[..., 0][m], t_plane[m], atol=1e-4)
    N = np.array(bufs["normal"])[np.array(valid).reshape(16, 16)]
    assert np.all((N * nd).sum(-1) > 0.9)
    assert _f(L.d2n_loss(bufs["normal"], bufs["depth_unbiased"], bufs["weight"], d, o)) < 0.05
