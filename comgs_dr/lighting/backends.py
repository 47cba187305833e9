"""Completion backends for lighting estimation: baseline fills, the trained net, diffusion.

Paper, "Lighting Estimation" / Appendix "Details of Lighting Estimation": the partial 360°
panorama traced at the placement is completed into LDR panoramas at EV 0, −2.5, −5 and fused
to HDR (``lighting.hdr.fuse_brackets``). Every backend here implements
``completion.CompletionBackend.complete(rgb [H,W,3], normal [H,W,3], mask [H,W], evs, label)
-> {ev: [H,W,3] float32 LDR}``:

* ``FillBackend("mean" | "push_pull" | "sh")``: non-learned fills of the EV-0 panorama
  (``hdr.mean_fill``/``push_pull_fill``/``sh_fill``, order 2) re-exposed with hdr's exposure
  model, so ``fuse_brackets`` of its output is exactly ``srgb_decode(filled)`` (no radiance
  above the EV-0 white level can appear: these are baselines).
* ``load_network_backend``: ``completion.NetworkBackend`` around the shipped ``CompletionNet``
  weights (``DEFAULT_WEIGHTS``; produced by ``comgs train-completion``).
* ``DiffusersBackend``: a local diffusers inpainting model (the paper fine-tunes Stable
  Diffusion 2.1 inpainting), with the EV prompt ξ_ev = ξ_b + (ev/EV_min)(ξ_d − ξ_b).
"""
from __future__ import annotations

import inspect
import json
from pathlib import Path

import numpy as np
import torch

from comgs_dr.core.colorspace import LUMA
from comgs_dr.lighting import completion, hdr
from comgs_dr.lighting.completion import (
    DEFAULT_EVS,
    EV_MIN,
    CompletionBackend,
    NetworkBackend,
)
from comgs_dr.lighting.torch_io import load_torch_file

__all__ = ["FILL_KINDS", "FillBackend", "BlendBackend", "DEFAULT_WEIGHTS", "LABEL_WEIGHTS",
           "LABEL_COLOUR_WEIGHTS", "net_sh_blend",
           "load_network_backend", "default_backend", "DiffusersBackend", "check_inputs"]

DEFAULT_WEIGHTS = Path(__file__).parent / "weights" / "completion.pt"
FILL_KINDS = ("mean", "push_pull", "sh")


def check_inputs(rgb, normal, mask, name: str):
    """NumPy rgb [H,W,3], normal [H,W,3], mask [H,W] (a trailing 1-channel axis is dropped);
    ValueError naming ``name`` otherwise (same rules as ``completion.NetworkBackend``)."""
    rgb, mask = np.asarray(rgb), np.asarray(mask)
    normal = np.zeros_like(rgb) if normal is None else np.asarray(normal)
    mask = mask[..., 0] if mask.ndim == 3 and mask.shape[-1] == 1 else mask
    if rgb.ndim != 3 or rgb.shape[-1] != 3 or normal.shape != rgb.shape \
            or mask.shape != rgb.shape[:2]:
        raise ValueError(f"{name}: need rgb/normal [H,W,3] and mask [H,W], got "
                         f"{rgb.shape}, {normal.shape}, {mask.shape}")
    return rgb, normal, mask


def _label_index(label) -> int:
    if isinstance(label, str):
        if label not in completion.LABELS:
            raise ValueError(f"unknown label {label!r} (expected one of "
                             f"{sorted(completion.LABELS)})")
        return completion.LABELS[label]
    return int(label)


# ---------------------------------------------------------------------------------------
# Baseline fills

class FillBackend(CompletionBackend):
    """Fill the EV-0 panorama (``hdr.<kind>_fill``), then re-expose it to every EV:
    out[ev] = expose(unexpose(filled, 0), ev). Observed pixels (mask > 0.5) are kept exactly
    at EV 0. Normals and the label are ignored. Zero coverage raises ValueError (the fills
    have nothing to extrapolate from)."""

    def __init__(self, kind: str = "push_pull", sh_order: int = 2):
        if kind not in FILL_KINDS:
            raise ValueError(f"FillBackend: unknown kind {kind!r} (expected one of "
                             f"{list(FILL_KINDS)})")
        self.kind, self.sh_order = kind, int(sh_order)

    def fill(self, rgb, mask) -> np.ndarray:
        """EV-0 fill [H, W, 3] float64 of rgb [H, W, 3] clipped to [0, 1] (NaN in holes ok)."""
        rgb = np.asarray(rgb, np.float64)
        m = np.clip(np.nan_to_num(np.asarray(mask, np.float64)), 0.0, 1.0)
        rgb = np.where(m[..., None] > 0.5, np.clip(rgb, 0.0, 1.0), 0.0)
        if self.kind == "mean":
            out = hdr.mean_fill(rgb, m)
        elif self.kind == "push_pull":
            out = hdr.push_pull_fill(rgb, m)
        else:
            out = hdr.sh_fill(rgb, m, order=self.sh_order)
        return np.clip(out, 0.0, 1.0)

    def complete(self, rgb, normal, mask, evs=DEFAULT_EVS, label=2) -> dict:
        rgb, _, mask = check_inputs(rgb, normal, mask, f"FillBackend({self.kind!r})")
        filled = self.fill(rgb, mask)                                     # [H, W, 3]
        radiance = hdr.unexpose(filled, 0.0)
        return {float(e): (filled if float(e) == 0.0 else hdr.expose(radiance, float(e)))
                .astype(np.float32) for e in evs}


# ---------------------------------------------------------------------------------------
# The trained completion network

def load_network_backend(path=None, resolution: tuple[int, int] | None = None
                         ) -> NetworkBackend:
    """``NetworkBackend`` of the ``CompletionNet`` checkpoint at ``path`` (default
    ``DEFAULT_WEIGHTS``). FileNotFoundError, saying how to produce weights, when missing;
    ``completion.WeightsError`` for an unusable file."""
    p = Path(DEFAULT_WEIGHTS if path is None else path)
    if not p.is_file():
        raise FileNotFoundError(
            f"completion weights not found: {p}. Train them with `comgs train-completion "
            f"--out {p}` (or pass a checkpoint saved by comgs_dr.lighting.completion."
            f"save_weights, e.g. --weights out/completion.pt), or use a non-learned backend "
            f"(--backend push_pull)")
    return NetworkBackend(completion.load_weights(p), resolution)


# ---------------------------------------------------------------------------------------
# Blends of backends (the default: net + SH fill)

class BlendBackend(CompletionBackend):
    """The first backend's brackets where the panorama is observed (and, with
    ``keep_lights``, where its EV-0 bracket is clipped, max channel ≥ ``sat``: a light it put
    in the hole); elsewhere in the hole the weighted mean of every backend's radiance per
    bracket: out[ev] = expose(Σ_i w_i · unexpose(b_i[ev], ev), ev), Σ w_i = 1.

    Model averaging: the net's hole is detailed but its colour wanders, the SH fill is smooth
    and right on average, and cannot hold a light (it stays below the EV-0 white), so
    averaging would only halve the net's lights: ``keep_lights`` keeps them.

    ``label_weights`` {label: weights} overrides ``weights`` for a completion label
    ("indoor", "outdoor", "unknown" or its index); members with weight 0 are not run.
    ``colour_weights`` (and ``label_colour_weights`` per label) mix the colour apart from
    the luminance, per bracket in radiance r_i = unexpose(b_i[ev], ev): C = Σ c_i · r_i,
    out = C · (Σ w_i Y(r_i)) / Y(C) per pixel (Y: luminance; the plain mean Σ w_i r_i where
    Y(C) is below 1e-6 of the bracket's white). None: out = Σ w_i r_i. Members with a colour
    weight > 0 are run even at luminance weight 0. Brackets are recoloured one by one: with
    ``keep_lights=False`` a pixel the first clips at EV 0 can be recoloured below white there
    and lose power in the fusion (as the plain mean could); ``keep_lights`` (the default)
    keeps such pixels the first's."""

    def __init__(self, members, weights=None, keep_lights: bool = True, sat: float = 0.95,
                 label_weights: dict | None = None, colour_weights=None,
                 label_colour_weights: dict | None = None):
        self.keep_lights, self.sat = bool(keep_lights), float(sat)
        members = list(members)
        if not members:
            raise ValueError("BlendBackend: need at least one backend")
        self.members = members
        self.weights = self._check_weights(weights)
        self.label_weights = {_label_index(k): self._check_weights(v, f"label {k!r}")
                              for k, v in (label_weights or {}).items()}
        self.colour_weights = (None if colour_weights is None
                               else self._check_weights(colour_weights, "colour"))
        self.label_colour_weights = {
            _label_index(k): self._check_weights(v, f"colour of label {k!r}")
            for k, v in (label_colour_weights or {}).items()}

    def _check_weights(self, weights, what: str = "") -> np.ndarray:
        n = len(self.members)
        w = np.full(n, 1.0 / n) if weights is None else np.asarray(weights, np.float64)
        if w.shape != (n,) or not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
            raise ValueError(f"BlendBackend: need {n} finite weights >= 0 with a positive "
                             f"sum{' for ' + what if what else ''}, got {weights}")
        return w / w.sum()

    def weights_for(self, label) -> np.ndarray:
        """The weights used for ``label`` (``label_weights`` if it names it, else ``weights``)."""
        return self.label_weights.get(_label_index(label), self.weights)

    def colour_weights_for(self, label) -> np.ndarray | None:
        """The colour weights for ``label`` (None: the luminance weights' own colour)."""
        return self.label_colour_weights.get(_label_index(label), self.colour_weights)

    @property
    def name(self) -> str:
        return "+".join(_backend_label(m) for m in self.members)

    def complete(self, rgb, normal, mask, evs=DEFAULT_EVS, label=2) -> dict:
        rgb, normal, mask = check_inputs(rgb, normal, mask, "BlendBackend")
        if self.keep_lights and 0.0 not in [float(e) for e in evs]:
            raise ValueError(f"BlendBackend(keep_lights=True) finds the first backend's lights "
                             f"in its EV-0 bracket: evs must include 0, got {list(evs)} (or "
                             f"pass keep_lights=False)")
        w, wc = self.weights_for(label), self.colour_weights_for(label)
        need = w if wc is None else w + wc
        use = [i for i in range(len(self.members)) if i == 0 or need[i] > 0]  # skip weight 0
        outs = [self.members[i].complete(rgb, normal, mask, evs=evs, label=label) for i in use]
        w, wc = w[use], (None if wc is None else wc[use])
        if len(outs) == 1 and w[0] > 0:
            return {e: np.asarray(v, np.float32) for e, v in outs[0].items()}
        seen = (np.asarray(mask) > 0.5)[..., None]                              # [H, W, 1]
        if self.keep_lights:                          # the first's lights in the hole stay whole
            seen = seen | (np.asarray(outs[0][0.0]).max(-1) >= self.sat)[..., None]
        res = {}
        for e in outs[0]:
            rads = [hdr.unexpose(np.asarray(o[e], np.float64), e) for o in outs]  # [H, W, 3]
            rad = sum(wi * r for wi, r in zip(w / w.sum(), rads))
            if wc is not None:                    # the mean's luminance in C's colour
                col = sum(ci * r for ci, r in zip(wc / wc.sum(), rads))          # [H, W, 3]
                lc, lm = col @ LUMA, rad @ LUMA                                 # [H, W]
                dark = 1e-6 * 2.0 ** -e        # 1e-6 of the bracket's white: colour is noise
                k = lm / np.maximum(lc, dark)
                rad = np.where((lc > dark)[..., None], col * k[..., None], rad)
            res[e] = np.where(seen, outs[0][e], hdr.expose(rad, e)).astype(np.float32)
        return res


def _backend_label(b) -> str:
    if isinstance(b, FillBackend):
        return b.kind
    return "net" if isinstance(b, NetworkBackend) else type(b).__name__


#: ``default_backend``'s luminance weights per label: outdoors the net's hole alone (its
#: colour: ``LABEL_COLOUR_WEIGHTS``), since the SH fill's smooth guess brightens the zenith
#: that an outdoor capture leaves in the hole; indoors the ½/½ blend.
LABEL_WEIGHTS = {"outdoor": (1.0, 0.0)}


#: ``net_sh_blend``'s colour in the hole per label, apart from its luminance: outdoors the
#: net's luminance (``LABEL_WEIGHTS``) in the colour of the ½ net + ½ SH mean, the colour
#: averaging the blend does indoors (the net's own colour wanders on maps it has not seen).
LABEL_COLOUR_WEIGHTS = {"outdoor": (0.5, 0.5)}
COLOUR_CHOICES = ("default", "mean", "first")


def net_sh_blend(net: CompletionBackend, colour: str = "default") -> "BlendBackend":
    """``net`` blended with the SH fill as ``estimate-light`` does: ½ + ½ in the hole
    (``BlendBackend``), ``net``'s luminance alone for label "outdoor" (``LABEL_WEIGHTS``).
    ``colour``: "default", outdoors the colour of the ½ + ½ mean (``LABEL_COLOUR_WEIGHTS``);
    "mean", each label's own mean (outdoors the net's colour); "first", the net's colour."""
    if colour not in COLOUR_CHOICES:
        raise ValueError(f"net_sh_blend: colour must be one of {COLOUR_CHOICES}, got {colour!r}")
    kw = {"default": {"label_colour_weights": LABEL_COLOUR_WEIGHTS}, "mean": {},
          "first": {"colour_weights": (1.0, 0.0),
                    "label_colour_weights": {k: (1.0, 0.0) for k in LABEL_WEIGHTS}}}[colour]
    return BlendBackend([net, FillBackend("sh")], label_weights=LABEL_WEIGHTS, **kw)


def default_backend(resolution: tuple[int, int] | None = None) -> "BlendBackend":
    """What ``estimate-light``, ``compose`` and the demo use: ``net_sh_blend`` of the
    shipped net."""
    return net_sh_blend(load_network_backend(resolution=resolution))


# ---------------------------------------------------------------------------------------
# Diffusion (diffusers)

def _import_diffusers():
    try:
        import diffusers  # optional dependency (extra 'diffusion')
    except ImportError as exc:
        raise ImportError("DiffusersBackend needs the 'diffusers' package: pip install "
                          "diffusers (or pip install comgs_dr[diffusion])") from exc
    return diffusers


def _as_embedding(x, name: str) -> torch.Tensor:
    t = torch.as_tensor(x)
    t = t[None] if t.dim() == 2 else t
    if t.dim() != 3 or t.shape[0] != 1 or not torch.is_floating_point(t):
        raise ValueError(f"DiffusersBackend: {name} must be a float [L, D] or [1, L, D] prompt "
                         f"embedding, got {tuple(t.shape)} {t.dtype}")
    return t


class DiffusersBackend(CompletionBackend):
    """Panorama completion with a local diffusers latent-inpainting model (the paper's
    fine-tuned Stable Diffusion 2.1 inpainting; weights are not shipped).

    ``source``: a local folder in the diffusers layout (``unet/``, ``vae/``, ``scheduler/``
    and optionally ``text_encoder/`` + ``tokenizer/``, loaded with ``local_files_only=True``;
    nothing is downloaded; the text encoder needs ``transformers`` and is skipped when
    ``xi_b``/``xi_d`` are given) or an already built pipeline (any object with ``unet``, ``vae``,
    ``scheduler`` and optionally ``text_encoder``/``tokenizer``, e.g. a
    ``StableDiffusionInpaintPipeline``).

    We run the inpainting denoising loop ourselves with those components, as
    ``StableDiffusionInpaintPipeline`` does for a 9-channel UNet: UNet input =
    [noisy latents 4, mask 1 (1 = to fill, nearest-downsampled), VAE latents of the masked
    image 4] (+ VAE latents of the normal map 4 when the UNet takes 13 channels: the paper
    feeds normals too; their exact encoding is not published, this is our choice). Reasons:
    the pipeline cannot be built without a CLIP text encoder/tokenizer (``transformers``),
    and the EV prompt is an *interpolated embedding* ξ_ev = ξ_b + (ev/EV_min)(ξ_d − ξ_b)
    (DiffusionLight's scheme), which we pass as ``encoder_hidden_states``. ξ_b/ξ_d come
    from the text encoder applied to ``prompts`` (the label word is formatted into them) or
    are given precomputed (``xi_b``, ``xi_d``; then the label is ignored).

    Every EV starts from the same noise (a fresh ``torch.Generator`` seeded with ``seed``),
    so the brackets are consistent and the output is deterministic; VAE encodings use the
    posterior mode. ``resolution`` (H, W) of the model input (default: the input size rounded
    up to a multiple of the latent grid; 512×1024 for SD 2.1 at its training size). The
    prediction is resized back (``completion.resize_equirect``) and blended with the input
    (``completion.blend_observed``): observed pixels come back exactly at EV 0.
    ``guidance_scale`` > 1 uses classifier-free guidance with ``negative`` embeddings (or
    the encoded empty prompt).
    """

    DEFAULT_PROMPTS = ("a 360 degree equirectangular panorama of an {label} scene",
                       "a dark, underexposed 360 degree equirectangular panorama of an "
                       "{label} scene")
    LABEL_WORDS = {0: "outdoor", 1: "indoor", 2: "unknown"}

    def __init__(self, source, *, xi_b=None, xi_d=None, negative=None,
                 prompts: tuple[str, str] | None = None, steps: int = 30,
                 guidance_scale: float = 1.0, seed: int = 0,
                 resolution: tuple[int, int] | None = None, ev_min: float = EV_MIN,
                 device=None):
        if isinstance(source, (str, Path)):
            comps = self._load_components(Path(source), text=xi_b is None)
        else:
            missing = [k for k in ("unet", "vae", "scheduler") if getattr(source, k, None) is None]
            if missing:
                raise ValueError(f"DiffusersBackend: the pipeline object lacks {missing}")
            comps = {k: getattr(source, k, None) for k in
                     ("unet", "vae", "scheduler", "text_encoder", "tokenizer")}
        self.unet, self.vae, self.scheduler = comps["unet"], comps["vae"], comps["scheduler"]
        self.text_encoder, self.tokenizer = comps.get("text_encoder"), comps.get("tokenizer")
        if (xi_b is None) != (xi_d is None):
            raise ValueError("DiffusersBackend: give both xi_b and xi_d, or neither")
        self.xi_b = None if xi_b is None else _as_embedding(xi_b, "xi_b")
        self.xi_d = None if xi_d is None else _as_embedding(xi_d, "xi_d")
        if self.xi_b is not None and self.xi_b.shape != self.xi_d.shape:
            raise ValueError(f"DiffusersBackend: xi_b {tuple(self.xi_b.shape)} and xi_d "
                             f"{tuple(self.xi_d.shape)} differ in shape")
        self.negative = None if negative is None else _as_embedding(negative, "negative")
        if self.xi_b is None and (self.text_encoder is None or self.tokenizer is None):
            raise ValueError("DiffusersBackend: no text encoder/tokenizer in the model; pass "
                             "precomputed prompt embeddings xi_b and xi_d")
        if steps < 1 or ev_min >= 0:
            raise ValueError(f"DiffusersBackend: need steps >= 1 and ev_min < 0, got "
                             f"{steps}, {ev_min}")
        self.prompts = tuple(prompts or self.DEFAULT_PROMPTS)
        self.steps, self.guidance_scale, self.seed = int(steps), float(guidance_scale), int(seed)
        self.ev_min, self.resolution = float(ev_min), resolution
        self.device = torch.device(device) if device is not None else self.unet.device
        self.dtype = self.unet.dtype
        cin = int(self.unet.config.in_channels)
        lat = int(self.vae.config.latent_channels)
        if cin not in (2 * lat + 1, 3 * lat + 1):
            raise ValueError(f"DiffusersBackend: an inpainting UNet takes {2 * lat + 1} "
                             f"(latents, mask, masked image) or {3 * lat + 1} (+ normals) input "
                             f"channels; this one takes {cin}")
        self.use_normals = cin == 3 * lat + 1
        self.vae_scale = 2 ** (len(self.vae.config.block_out_channels) - 1)
        if resolution is not None:
            self.check_size(*resolution)

    # -- loading --

    EMBEDDINGS_FILE = "ev_embeddings.pt"

    @classmethod
    def from_dir(cls, path, **kwargs) -> "DiffusersBackend":
        """Backend of a local model folder; when it holds ``ev_embeddings.pt``
        (``torch.save({"xi_b": [L, D], "xi_d": [L, D]})``) those embeddings are used."""
        p = Path(path)
        emb = p / cls.EMBEDDINGS_FILE
        if emb.is_file() and "xi_b" not in kwargs:
            d = load_torch_file(emb, None, "DiffusersBackend embeddings file")
            if not isinstance(d, dict) or not {"xi_b", "xi_d"} <= set(d):
                raise ValueError(f"DiffusersBackend: {emb} must hold a dict with 'xi_b' and "
                                 f"'xi_d'")
            kwargs.update(xi_b=d["xi_b"], xi_d=d["xi_d"])
        return cls(p, **kwargs)

    @staticmethod
    def _load_components(path: Path, text: bool = True) -> dict:
        diffusers = _import_diffusers()
        if not path.is_dir():
            raise FileNotFoundError(f"DiffusersBackend: model folder not found: {path}")
        for sub in ("unet", "vae", "scheduler"):
            if not (path / sub).is_dir():
                raise FileNotFoundError(f"DiffusersBackend: {path} has no '{sub}/' folder "
                                        f"(expected the diffusers layout)")
        kw = {"local_files_only": True}
        mkw = {**kw, "low_cpu_mem_usage": False}       # no 'accelerate' needed
        sched_cfg = json.loads((path / "scheduler" / "scheduler_config.json").read_text())
        sched_cls = getattr(diffusers, sched_cfg.get("_class_name", "DDIMScheduler"))
        comps = {"unet": diffusers.UNet2DConditionModel.from_pretrained(path, subfolder="unet",
                                                                        **mkw),
                 "vae": diffusers.AutoencoderKL.from_pretrained(path, subfolder="vae", **mkw),
                 "scheduler": sched_cls.from_pretrained(path, subfolder="scheduler", **kw)}
        if text and (path / "text_encoder").is_dir() and (path / "tokenizer").is_dir():
            index = path / "model_index.json"
            names = json.loads(index.read_text()) if index.is_file() else {}
            try:
                import transformers  # optional: only for models with a text encoder
            except ImportError as exc:
                raise ImportError(f"DiffusersBackend: {path} holds a text encoder; loading it "
                                  f"needs the 'transformers' package") from exc
            enc = getattr(transformers, names.get("text_encoder", [None, "CLIPTextModel"])[1])
            tok = getattr(transformers, names.get("tokenizer", [None, "CLIPTokenizer"])[1])
            comps["text_encoder"] = enc.from_pretrained(path, subfolder="text_encoder", **kw)
            comps["tokenizer"] = tok.from_pretrained(path, subfolder="tokenizer", **kw)
        return comps

    # -- sizes and prompts --

    @property
    def multiple(self) -> int:
        return self.vae_scale * 2 ** (len(self.unet.config.block_out_channels) - 1)

    def check_size(self, h: int, w: int):
        m = self.multiple
        if h % m or w % m:
            raise ValueError(f"DiffusersBackend: model input {h}x{w} must be a multiple of {m}")

    def net_size(self, h: int, w: int) -> tuple[int, int]:
        if self.resolution is not None:
            return tuple(self.resolution)
        m = self.multiple
        return max(m, -(-h // m) * m), max(m, -(-w // m) * m)

    @torch.no_grad()
    def _encode_text(self, text: str) -> torch.Tensor:
        ids = self.tokenizer(text, padding="max_length", max_length=self.tokenizer.model_max_length,
                             truncation=True, return_tensors="pt").input_ids
        return self.text_encoder(ids.to(self.text_encoder.device))[0]

    def embeddings(self, label=2) -> tuple[torch.Tensor, torch.Tensor]:
        """(ξ_b, ξ_d) [1, L, D] for ``label`` (precomputed ones, or encoded prompts)."""
        if self.xi_b is not None:
            return self.xi_b, self.xi_d
        word = self.LABEL_WORDS.get(_label_index(label), "unknown")
        return tuple(self._encode_text(p.format(label=word)) for p in self.prompts)

    def ev_embedding(self, ev: float, label=2) -> torch.Tensor:
        """ξ_ev = ξ_b + (ev/EV_min)(ξ_d − ξ_b) [1, L, D]."""
        xb, xd = self.embeddings(label)
        t = float(ev) / self.ev_min
        return (xb + t * (xd - xb)).to(self.device, self.dtype)

    # -- the denoising loop --

    def _latents(self, img: torch.Tensor) -> torch.Tensor:   # [1, 3, h, w] in [-1, 1]
        lat = self.vae.encode(img).latent_dist.mode()
        return lat * float(self.vae.config.scaling_factor)

    @torch.no_grad()
    def _denoise(self, cond_img, mask_lat, extra, emb) -> torch.Tensor:
        """One inpainting run; returns the decoded image [1, 3, h, w] in [0, 1]."""
        gen = torch.Generator(device="cpu").manual_seed(self.seed)
        lat_ch = int(self.vae.config.latent_channels)
        shape = (1, lat_ch, *mask_lat.shape[-2:])
        sch = self.scheduler
        sch.set_timesteps(self.steps, device=self.device)
        latents = torch.randn(shape, generator=gen, dtype=self.dtype).to(self.device)
        latents = latents * float(sch.init_noise_sigma)
        cfg = self.guidance_scale > 1.0
        if cfg:
            neg = self.negative if self.negative is not None else (
                self._encode_text("") if self.text_encoder is not None else None)
            if neg is None:
                raise ValueError("DiffusersBackend: guidance_scale > 1 needs negative embeddings")
            emb = torch.cat([neg.to(emb), emb])
        step_kw = {"generator": gen} if "generator" in inspect.signature(sch.step).parameters \
            else {}
        for t in sch.timesteps:
            x = torch.cat([latents] * 2) if cfg else latents
            x = sch.scale_model_input(x, t)
            cond = torch.cat([mask_lat, cond_img] + extra, 1)
            x = torch.cat([x, cond.expand(x.shape[0], -1, -1, -1)], 1)
            eps = self.unet(x, t, encoder_hidden_states=emb).sample
            if cfg:
                e_u, e_c = eps.chunk(2)
                eps = e_u + self.guidance_scale * (e_c - e_u)
            latents = sch.step(eps, t, latents, **step_kw).prev_sample
        img = self.vae.decode(latents / float(self.vae.config.scaling_factor)).sample
        return (img.float() / 2 + 0.5).clamp(0.0, 1.0)

    @torch.no_grad()
    def complete(self, rgb, normal, mask, evs=DEFAULT_EVS, label=2) -> dict:
        rgb, normal, mask = check_inputs(rgb, normal, mask, "DiffusersBackend")
        dev, dt = self.device, self.dtype

        def t(a):   # [H, W, C] -> [1, C, H, W] float32
            return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32).permute(
                2, 0, 1)[None]

        h, w = rgb.shape[:2]
        r, n, m = completion._sanitize(t(rgb), t(normal), t(mask[..., None]))
        hn, wn = self.net_size(h, w)
        rr, nn_, mm = (completion.resize_equirect(a, hn, wn) for a in (r, n, m))
        hole = (mm < 0.5).to(torch.float32)                          # [1, 1, hn, wn] 1 = fill
        masked = (rr * 2.0 - 1.0) * (1.0 - hole)                     # [-1, 1], holes 0
        cond_img = self._latents(masked.to(dev, dt))
        mask_lat = torch.nn.functional.interpolate(
            hole, size=cond_img.shape[-2:], mode="nearest").to(dev, dt)
        extra = [self._latents(nn_.clamp(-1, 1).to(dev, dt))] if self.use_normals else []
        out = {}
        for e in evs:
            pred = self._denoise(cond_img, mask_lat, extra, self.ev_embedding(e, label))
            pred = completion.resize_equirect(pred.cpu(), h, w)
            ev = torch.full((1,), float(e))
            img = completion.blend_observed(r, m, pred.clamp(0, 1), ev)
            out[float(e)] = img[0].permute(1, 2, 0).numpy().astype(np.float32)
        return out
