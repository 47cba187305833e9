"""EV-conditioned panorama completion network (a small CPU stand-in for the paper's diffusion).

Paper, "Lighting Estimation" / Appendix "Details of Lighting Estimation": the partial 360°
panorama (equirect, Z-up, v = 0 the top row; RGB, normals, alpha mask) traced from the object's
placement is completed by a fine-tuned Stable Diffusion into LDR panoramas at EV 0, −2.5, −5,
fused to HDR by ``lighting.hdr``. Its EV prompt ξ_ev = ξ_b + (ev/EV_min)(ξ_d − ξ_b), EV_min = −5,
interpolates a base (EV 0) and a dark (EV −5) embedding; an indoor/outdoor token is added.
Here a compact U-Net does the job:

* ``SphericalPad2d`` before every convolution (no zero padding): circular in u, "polar" in v:
  across a pole the neighbour of (u, v < 0) is (u + ½, −v), i.e. row −1−k is row k rolled by
  W/2 (``padding="replicate"`` is the simpler option). So the net is exactly equivariant to
  horizontal circular shifts by multiples of 2**levels pixels. Polar padding needs an even
  width at every level: H % 2**levels == 0, W % 2**(levels+1) == 0 (``config.multiple``).
* GroupNorm + SiLU residual blocks, all FiLM-modulated by cond = MLP(ξ_ev + label embedding)
  (label 0 outdoor, 1 indoor, 2 unknown); pixel-centred stride-2 4×4 convolutions down,
  nearest ×2 + 3×3 up; a global-context branch (solid-angle-weighted bottleneck mean,
  broadcast back) for large holes; two latitude channels (cos θ, sin θ) added to the input.
* Output LDR in [0, 1] (sigmoid); completed = k·obs + (1 − k)·pred, k = mask. At EV ≠ 0 ``obs``
  is the EV-0 input re-exposed with ``lighting.hdr``'s model clip(sRGB(linear·2**ev), 0, 1),
  and at EV < 0 pixels saturated at EV 0 (max channel ≥ ``SATURATION``) get k = 0: their
  radiance is unknown. (Pasting EV-0 pixels into the EV −5 image would make the HDR 32× off.)

No dropout and no running statistics: train/eval modes agree and inference is deterministic.
``NetworkBackend`` puts a net behind ``CompletionBackend`` (NumPy [H, W, C], any size), where a
diffusion backend can plug in later.
"""
from __future__ import annotations

import abc
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from comgs_dr.core.colorspace import srgb_decode, srgb_encode
from comgs_dr.lighting.hdr import push_pull_fill
from comgs_dr.lighting.torch_io import load_torch_file
from comgs_dr.lighting.torch_io import torch_load_error  # noqa: F401 (stages.train_completion)

__all__ = ["FORMAT_VERSION", "DEFAULT_EVS", "EV_MIN", "LABELS", "SATURATION", "CompletionConfig",
           "SphericalPad2d", "SConv2d", "FiLM", "ResBlock", "GlobalContext", "EVEmbedding",
           "CompletionNet", "CompletionOutput", "blend_observed", "expose_ldr", "fill_prior",
           "resize_equirect", "save_weights", "load_weights", "WeightsError",
           "count_parameters", "CompletionBackend", "NetworkBackend"]

FORMAT_VERSION, _FORMAT = "comgs-completion-v2", "comgs_dr.lighting.completion"
SUPPORTED_VERSIONS = ("comgs-completion-v1", FORMAT_VERSION)   # v1: no prior, train_resolution
DEFAULT_EVS, EV_MIN = (0.0, -2.5, -5.0), -5.0
LABELS = {"outdoor": 0, "indoor": 1, "unknown": 2}
SATURATION = 0.999   # EV-0 LDR max channel at/above which radiance is unknown (clipped)


@dataclass(frozen=True)
class CompletionConfig:
    in_channels: int = 7            # rgb 3 + normal 3 + mask 1 (latitude channels are added inside)
    out_channels: int = 3
    base_channels: int = 32
    levels: int = 4                 # number of stride-2 downsamplings
    channel_mults: tuple = (1, 2, 4, 4, 4)   # per resolution, len = levels + 1
    embed_dim: int = 64
    groups: int = 8                 # GroupNorm groups (gcd with the channel count)
    ev_min: float = EV_MIN
    n_labels: int = 3
    padding: str = "polar"          # vertical padding: "polar" or "replicate"
    latitude_channels: bool = True
    train_resolution: tuple = (64, 128)      # (H, W) the weights were trained at; inference size
    prior: str = "none"             # "push_pull": residual on the push-pull fill (see fill_prior)
    version: str = FORMAT_VERSION

    def __post_init__(self):
        object.__setattr__(self, "channel_mults", tuple(int(m) for m in self.channel_mults))
        object.__setattr__(self, "train_resolution", tuple(int(m) for m in self.train_resolution))
        if (self.levels < 1 or len(self.channel_mults) != self.levels + 1 or self.ev_min >= 0
                or self.padding not in ("polar", "replicate") or self.prior not in (
                    "none", "push_pull") or min(
                    self.base_channels, self.embed_dim, self.groups, *self.channel_mults) < 1):
            raise ValueError(f"CompletionConfig: invalid values (need levels >= 1, "
                             f"len(channel_mults) == levels + 1, ev_min < 0, padding "
                             f"'polar'/'replicate', prior 'none'/'push_pull', positive "
                             f"sizes): {self}")

    @property
    def channels(self) -> list[int]:
        return [self.base_channels * m for m in self.channel_mults]

    @property
    def multiple(self) -> tuple[int, int]:
        """(height, width) multiples an input must have."""
        return 2 ** self.levels, 2 ** (self.levels + 1)

    def to_dict(self) -> dict:
        return {**asdict(self), "channel_mults": list(self.channel_mults),
                "train_resolution": list(self.train_resolution)}

    @classmethod
    def from_dict(cls, d: dict) -> "CompletionConfig":
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"CompletionConfig: unknown fields {sorted(unknown)}")
        return cls(**d)


# ---- Building blocks ----

class SphericalPad2d(nn.Module):
    """Pad [..., H, W] by ``pad``: circular in u; in v "polar" (row −1−k = row k rolled by W/2,
    row H+k = row H−1−k rolled by W/2; W even, pad ≤ H) or "replicate"."""

    def __init__(self, pad: int = 1, vertical: str = "polar"):
        super().__init__()
        if vertical not in ("polar", "replicate"):
            raise ValueError("SphericalPad2d: vertical must be 'polar' or 'replicate'")
        self.pad, self.vertical = int(pad), vertical

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p, (h, w) = self.pad, x.shape[-2:]
        if p == 0:
            return x
        if p > h or p > w:
            raise ValueError(f"SphericalPad2d: pad {p} larger than the image {h}x{w}")
        if self.vertical == "polar":
            if w % 2:
                raise ValueError(f"SphericalPad2d: polar padding needs an even width, got {w}")
            top = x[..., :p, :].flip(-2).roll(w // 2, dims=-1)
            bot = x[..., h - p:, :].flip(-2).roll(w // 2, dims=-1)
            x = torch.cat([top, x, bot], dim=-2)
        else:
            x = F.pad(x, (0, 0, p, p), mode="replicate")
        return torch.cat([x[..., -p:], x, x[..., :p]], dim=-1)


class SConv2d(nn.Module):
    """Conv2d with spherical padding of (k − 1)//2 (k = 3: same size; k = 4, stride 2: half)."""

    def __init__(self, cin: int, cout: int, k: int = 3, stride: int = 1, vertical: str = "polar"):
        super().__init__()
        self.pad = SphericalPad2d((k - 1) // 2, vertical)
        self.conv = nn.Conv2d(cin, cout, k, stride=stride, padding=0)

    def forward(self, x):
        return self.conv(self.pad(x))


class FiLM(nn.Module):
    """x · (1 + γ(cond)) + β(cond), per channel; zero-initialised (identity at start)."""

    def __init__(self, cond_dim: int, channels: int):
        super().__init__()
        self.lin = nn.Linear(cond_dim, 2 * channels)
        nn.init.zeros_(self.lin.weight), nn.init.zeros_(self.lin.bias)

    def forward(self, x, cond):
        g, b = self.lin(cond).chunk(2, dim=-1)
        return x * (1.0 + g[..., None, None]) + b[..., None, None]


def _gn(c: int, groups: int) -> nn.GroupNorm:
    return nn.GroupNorm(math.gcd(groups, c), c)


class ResBlock(nn.Module):
    """GN → SiLU → conv → GN → FiLM → SiLU → conv, plus a (1×1) skip."""

    def __init__(self, cin, cout, cond_dim, groups=8, vertical="polar"):
        super().__init__()
        self.n1, self.c1 = _gn(cin, groups), SConv2d(cin, cout, 3, vertical=vertical)
        self.n2, self.film, self.c2 = (_gn(cout, groups), FiLM(cond_dim, cout),
                                       SConv2d(cout, cout, 3, vertical=vertical))
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x, cond):
        h = self.c1(F.silu(self.n1(x)))
        h = self.c2(F.silu(self.film(self.n2(h), cond)))
        return self.skip(x) + h


class GlobalContext(nn.Module):
    """Adds MLP([solid-angle-weighted mean of x, cond]) to every pixel."""

    def __init__(self, channels: int, cond_dim: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(channels + cond_dim, channels), nn.SiLU(),
                                 nn.Linear(channels, channels))

    def forward(self, x, cond):
        h = x.shape[-2]
        w = torch.sin(math.pi * (torch.arange(h, dtype=x.dtype, device=x.device) + 0.5) / h)
        pooled = (x.mean(-1) * (w / w.sum())).sum(-1)                       # [B, C]
        return x + self.mlp(torch.cat([pooled, cond], -1))[..., None, None]


class EVEmbedding(nn.Module):
    """ξ_ev = ξ_b + (ev/EV_min)(ξ_d − ξ_b), computed as (1 − t)ξ_b + tξ_d: exact at t = 0, ½, 1."""

    def __init__(self, dim: int, ev_min: float = EV_MIN):
        super().__init__()
        self.ev_min = float(ev_min)
        self.xi_b = nn.Parameter(torch.randn(dim) * 0.5)
        self.xi_d = nn.Parameter(torch.randn(dim) * 0.5)

    def forward(self, ev: torch.Tensor) -> torch.Tensor:                    # [B] -> [B, D]
        t = (ev.to(self.xi_b.dtype) / self.ev_min)[..., None]
        return (1.0 - t) * self.xi_b + t * self.xi_d


# ---- Exposure-aware blend of observed pixels ----

def expose_ldr(rgb: torch.Tensor, ev: torch.Tensor) -> torch.Tensor:
    """EV-0 LDR [B, 3, H, W] re-exposed to ``ev`` [B]; exactly ``rgb`` where ev == 0."""
    e = ev.to(rgb.dtype).reshape(-1, 1, 1, 1)
    out = srgb_encode(srgb_decode(rgb) * torch.exp2(e)).clamp(0.0, 1.0)
    return torch.where(e == 0, rgb, out)


def blend_observed(rgb, mask, pred, ev, saturation: float = SATURATION):
    """o where mask > 0.5 (observed, as in the fills), else pred; o is the observation
    re-exposed to ``ev`` (expose_ldr), except at EV < 0 in channels saturated at EV 0, whose
    radiance is only bounded below by the clip: there o = max(pred, expose_ldr(rgb, ev)) (the
    prediction, made consistent with the observation; unsaturated channels stay exact).

    A hard threshold, not an alpha blend: the traced colour of a partly covered pixel is the
    radiance seen there, and blending the prediction into the many (~40 %) partly covered
    pixels of a surfel trace adds colour error."""
    e = ev.to(rgb.dtype).reshape(-1, 1, 1, 1)
    seen = expose_ldr(rgb, ev)
    clipped = (e < 0) & (rgb >= saturation)                              # [B, 3, H, W]
    o = torch.where(clipped, torch.maximum(pred, seen), seen)
    return torch.where(mask > 0.5, o, pred)


# ---- The network ----

class CompletionOutput(NamedTuple):
    completed: torch.Tensor   # [B, 3, H, W] observed pixels kept (re-exposed)
    pred: torch.Tensor        # [B, 3, H, W] raw network prediction in [0, 1]


def _batch_vec(v, b: int, dtype, device) -> torch.Tensor:
    t = torch.as_tensor(v, dtype=dtype, device=device).reshape(-1)
    t = t.expand(b) if t.numel() == 1 else t
    if t.numel() != b:
        raise ValueError(f"CompletionNet: expected a scalar or {b} values, got {t.numel()}")
    return t


def _sanitize(rgb, normal, mask):
    """Mask clamped to [0, 1]; rgb (clamped to [0, 1]) and normals zeroed where it is 0."""
    m = torch.nan_to_num(mask).clamp(0.0, 1.0)
    z = torch.zeros((), dtype=rgb.dtype, device=rgb.device)
    return (torch.where(m > 0, torch.nan_to_num(rgb).clamp(0.0, 1.0), z),
            torch.where(m > 0, torch.nan_to_num(normal), z), m)


class CompletionNet(nn.Module):
    def __init__(self, config: CompletionConfig | None = None):
        super().__init__()
        c = self.config = config or CompletionConfig()
        ch, e, g, v, n = c.channels, c.embed_dim, c.groups, c.padding, c.levels
        self.ev_embed = EVEmbedding(e, c.ev_min)
        self.label_embed = nn.Embedding(c.n_labels, e)
        self.cond_mlp = nn.Sequential(nn.Linear(e, e), nn.SiLU(), nn.Linear(e, e))
        cin = c.in_channels + (2 if c.latitude_channels else 0) + (3 if c.prior != "none" else 0)
        self.stem = SConv2d(cin, ch[0], 3, vertical=v)
        self.enc = nn.ModuleList(ResBlock(ch[i], ch[i], e, g, v) for i in range(n))
        self.down = nn.ModuleList(SConv2d(ch[i], ch[i + 1], 4, 2, v) for i in range(n))
        self.mid1, self.mid2 = ResBlock(ch[n], ch[n], e, g, v), ResBlock(ch[n], ch[n], e, g, v)
        self.context = GlobalContext(ch[n], e)
        self.up = nn.ModuleList(SConv2d(ch[i + 1], ch[i], 3, vertical=v) for i in range(n))
        self.dec = nn.ModuleList(ResBlock(2 * ch[i], ch[i], e, g, v) for i in range(n))
        self.out_norm, self.out_conv = _gn(ch[0], g), SConv2d(ch[0], c.out_channels, 3, vertical=v)
        if c.prior != "none":   # residual on the prior: exactly the prior at initialisation
            nn.init.zeros_(self.out_conv.conv.weight), nn.init.zeros_(self.out_conv.conv.bias)

    def condition(self, ev, label, batch: int = 1) -> torch.Tensor:
        """Condition vector [B, D] = MLP(ξ_ev + label embedding)."""
        p = self.ev_embed.xi_b
        if isinstance(label, str):
            label = LABELS[label]
        ev = _batch_vec(ev, batch, p.dtype, p.device)
        lab = _batch_vec(label, batch, torch.long, p.device)
        if ((lab < 0) | (lab >= self.config.n_labels)).any():
            raise ValueError(f"CompletionNet: labels must be in [0, {self.config.n_labels})")
        return self.cond_mlp(self.ev_embed(ev) + self.label_embed(lab))

    def check_size(self, h: int, w: int):
        mh, mw = self.config.multiple
        if h % mh or w % mw:
            raise ValueError(f"CompletionNet: input {h}x{w} must be a multiple of {mh}x{mw} "
                             f"(use NetworkBackend or resize_equirect)")

    def forward(self, rgb, normal, mask, ev=0.0, label=2, prior=None) -> CompletionOutput:
        """rgb [B,3,H,W] EV-0 LDR, normal [B,3,H,W], mask [B,1,H,W] or [B,H,W] (1 = observed);
        ``prior`` [B,3,H,W]: the EV-0 prior fill (``fill_prior``; computed when None)."""
        mask = mask[:, None] if mask.dim() == 3 else mask
        b, _, h, w = rgb.shape
        if normal.shape != rgb.shape or mask.shape != (b, 1, h, w) or rgb.shape[1] != 3:
            raise ValueError(f"CompletionNet: bad shapes rgb {tuple(rgb.shape)}, normal "
                             f"{tuple(normal.shape)}, mask {tuple(mask.shape)}")
        self.check_size(h, w)
        rgb, normal, m = _sanitize(rgb, normal, mask)
        cond = self.condition(ev, label, b)
        x = [rgb, normal, m]
        if self.config.prior != "none":
            prior = fill_prior(rgb, m) if prior is None else prior.to(rgb.dtype)
            x.append(prior)
        if self.config.latitude_channels:
            th = math.pi * (torch.arange(h, dtype=rgb.dtype, device=rgb.device) + 0.5) / h
            lat = torch.stack([torch.cos(th), torch.sin(th)])[None, :, :, None]
            x.append(lat.expand(b, 2, h, w))
        x = self.stem(torch.cat(x, 1))
        skips = []
        for blk, down in zip(self.enc, self.down):
            x = blk(x, cond)
            skips.append(x)
            x = down(x)
        x = self.mid2(self.context(self.mid1(x, cond), cond), cond)
        for i in reversed(range(self.config.levels)):
            x = self.up[i](F.interpolate(x, scale_factor=2.0, mode="nearest"))
            x = self.dec[i](torch.cat([x, skips[i]], 1), cond)
        ev_t = _batch_vec(ev, b, rgb.dtype, rgb.device)
        logits = self.out_conv(F.silu(self.out_norm(x)))
        if self.config.prior != "none":   # the prior re-exposed to ev, in logit space
            base = expose_ldr(prior, ev_t).clamp(1e-3, 1 - 1e-3)
            logits = logits + torch.log(base / (1 - base))
        pred = torch.sigmoid(logits)
        return CompletionOutput(blend_observed(rgb, m, pred, ev_t), pred)

    @torch.no_grad()
    def complete(self, rgb, normal, mask, evs=DEFAULT_EVS, label=2) -> dict:
        """{float(ev): completed [B, 3, H, W]} (deterministic; train/eval modes agree)."""
        return {float(e): self(rgb, normal, mask, float(e), label).completed for e in evs}


def fill_prior(rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Push-pull fill (``hdr.push_pull_fill``) of each EV-0 panorama [B,3,H,W] with mask
    [B,1,H,W], as a constant input (no gradient); mid-grey where nothing is observed."""
    out = []
    for r, m in zip(rgb.detach().cpu().numpy(), mask.detach().cpu().numpy()):
        mm = m[0]
        out.append(push_pull_fill(r.transpose(1, 2, 0), mm).transpose(2, 0, 1)
                   if (mm > 0.5).any() else np.full_like(r, 0.5))
    return torch.as_tensor(np.stack(out), dtype=rgb.dtype, device=rgb.device).clamp(0, 1)


def count_parameters(model: nn.Module, trainable_only: bool = True) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)


# ---- Save / load ----

class WeightsError(ValueError):
    """A completion checkpoint that cannot be used (format, version or config mismatch)."""


def save_weights(model: CompletionNet, path) -> Path:
    """torch.save of {format, version, config, state_dict} (loadable with weights_only)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sd = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    torch.save({"format": _FORMAT, "version": model.config.version,
                "config": model.config.to_dict(), "state_dict": sd}, path)
    return path


def load_weights(path, config: CompletionConfig | None = None,
                 map_location="cpu") -> CompletionNet:
    """CompletionNet (eval mode) from ``save_weights``. FileNotFoundError if missing;
    WeightsError for a non-checkpoint, a version != FORMAT_VERSION, a stored config != ``config``
    (when given) or a state dict that does not fit its config."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"completion weights not found: {path}")
    ckpt = load_torch_file(path, _FORMAT, "completion checkpoint", map_location, WeightsError)
    if ckpt.get("version") not in SUPPORTED_VERSIONS:
        raise WeightsError(f"{path}: checkpoint version {ckpt.get('version')!r} is not "
                           f"supported (expected one of {SUPPORTED_VERSIONS})")
    try:
        stored = CompletionConfig.from_dict(dict(ckpt["config"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise WeightsError(f"{path}: invalid config in checkpoint ({exc})") from exc
    if config is not None and config != stored:
        diff = {k: (v, getattr(stored, k)) for k, v in asdict(config).items()
                if getattr(stored, k) != v}
        raise WeightsError(f"{path}: config mismatch, field: (expected, stored) = {diff}")
    model = CompletionNet(stored)
    try:
        model.load_state_dict(ckpt["state_dict"], strict=True)
    except (KeyError, RuntimeError) as exc:
        raise WeightsError(f"{path}: state dict does not match its config ({exc})") from exc
    return model.eval()


# ---- Backends (NumPy [H, W, C] in/out) ----

def _lin_index(n_in: int, n_out: int, wrap: bool, device):
    pos = (torch.arange(n_out, dtype=torch.float64) + 0.5) * (n_in / n_out) - 0.5
    f = pos - torch.floor(pos)
    i0 = torch.floor(pos).long()
    i0, i1 = (i0 % n_in, (i0 + 1) % n_in) if wrap else (i0.clamp(0, n_in - 1),
                                                        (i0 + 1).clamp(0, n_in - 1))
    return i0.to(device), i1.to(device), f.to(device)


def resize_equirect(x: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Bilinear resize of [..., H, W] equirect maps: wraps in u, clamps in v (pixel centres)."""
    if tuple(x.shape[-2:]) == (h, w):
        return x
    i0, i1, f = _lin_index(x.shape[-1], w, True, x.device)
    f = f.to(x.dtype)
    x = x.index_select(-1, i0) * (1 - f) + x.index_select(-1, i1) * f
    i0, i1, f = _lin_index(x.shape[-2], h, False, x.device)
    f = f.to(x.dtype)[:, None]
    return x.index_select(-2, i0) * (1 - f) + x.index_select(-2, i1) * f


class CompletionBackend(abc.ABC):
    """Completes a partial EV-0 LDR panorama into LDR panoramas at several EVs."""

    @abc.abstractmethod
    def complete(self, rgb: np.ndarray, normal: np.ndarray, mask: np.ndarray,
                 evs=DEFAULT_EVS, label: int = 2) -> dict:
        """rgb [H,W,3] float32 in [0,1], normal [H,W,3], mask [H,W] -> {ev: [H,W,3] float32}."""


class NetworkBackend(CompletionBackend):
    """CompletionNet as a backend. Inputs are resized (``resize_equirect``) to ``resolution``
    (default: the size the weights were trained at, ``config.train_resolution``; ``"input"``:
    the input's size rounded up to the next valid multiple); the prediction is resized back and
    blended with the original pixels at the original size, so observed pixels come back exactly
    (EV 0)."""

    def __init__(self, model: CompletionNet, resolution: tuple[int, int] | str | None = None):
        self.model = model.eval()
        if resolution is None:
            resolution = model.config.train_resolution
        if resolution == "input":
            resolution = None
        if resolution is not None:
            model.check_size(*resolution)
        self.resolution = resolution

    def net_size(self, h: int, w: int) -> tuple[int, int]:
        if self.resolution is not None:
            return self.resolution
        mh, mw = self.model.config.multiple
        return max(mh, -(-h // mh) * mh), max(mw, -(-w // mw) * mw)

    @torch.no_grad()
    def complete(self, rgb, normal, mask, evs=DEFAULT_EVS, label=2) -> dict:
        rgb, normal, mask = np.asarray(rgb), np.asarray(normal), np.asarray(mask)
        mask = mask[..., 0] if mask.ndim == 3 and mask.shape[-1] == 1 else mask
        if rgb.ndim != 3 or rgb.shape[-1] != 3 or normal.shape != rgb.shape \
                or mask.shape != rgb.shape[:2]:
            raise ValueError(f"NetworkBackend: need rgb/normal [H,W,3] and mask [H,W], got "
                             f"{rgb.shape}, {normal.shape}, {mask.shape}")
        p = next(self.model.parameters())
        dt, dev = p.dtype, p.device

        def t(a):   # [H, W, C] -> [1, C, H, W]
            return torch.as_tensor(np.ascontiguousarray(a), dtype=dt, device=dev).permute(
                2, 0, 1)[None]

        h, w = rgb.shape[:2]
        r, n, m = _sanitize(t(rgb), t(normal), t(mask[..., None]))
        hn, wn = self.net_size(h, w)
        rr, nn_, mm = (resize_equirect(a, hn, wn) for a in (r, n, m))
        prior = fill_prior(rr, mm) if self.model.config.prior != "none" else None
        out = {}
        for e in evs:
            pred = resize_equirect(self.model(rr, nn_, mm, float(e), label, prior).pred, h, w)
            ev = torch.full((1,), float(e), dtype=dt, device=dev)
            img = blend_observed(r, m, pred.clamp(0, 1), ev)
            out[float(e)] = img[0].permute(1, 2, 0).cpu().numpy().astype(np.float32)
        return out
