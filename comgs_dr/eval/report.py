"""``comgs report RUN_DIR``: one self-contained HTML page for any run folder.

It reads what the stages wrote (no rendering): every ``*metrics.jsonl`` below the folder
(``core.runlog``: reconstruct, decompose, estimate-light, compose, render-comp,
train-completion, the demo) is plotted as error (PSNR, loss) against wall time, one panel per
stage, with matplotlib; the summaries (``train_log.json``, ``metrics_*.json``, ``edit.json``,
estimate-light ``*.json``, ``demo.json``) become tables; the pictures (the demo's
``comparison.png`` / ``envmaps.png``, estimate-light previews, the first frames of
``renders/<variant>/`` and ``render_<split>/``) are inlined. Every image is a base64 PNG
``data:`` URI, so the file opens in any browser, offline, alone.
"""
from __future__ import annotations

import base64
import html
import io
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from comgs_dr.core import runlog

MAX_WIDTH = 1400          # wider pictures are downscaled before inlining
_PSNR_KEYS = ("psnr_test", "psnr_train", "psnr_select", "psnr")
_LOSS_KEYS = ("val_ev0", "val_ev", "loss")


@dataclass
class ReportConfig:
    """Settings of ``comgs report`` (:func:`write_report`; the output file is ``--out``).

    title: the page's heading and window title (default None: ``comgs report: <folder
    name>``).
    """
    title: str | None = None


# ----------------------------------------------------------------------------- building blocks

def png_data_uri(img) -> str:
    """``data:image/png;base64,...`` of a PIL image, an [H, W(, C)] array in [0, 1] / uint8,
    or a PNG/JPEG file path (downscaled to ``MAX_WIDTH``)."""
    if isinstance(img, (str, Path)):
        img = Image.open(img)
        img.load()
    elif isinstance(img, np.ndarray):
        a = img if img.dtype == np.uint8 else (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
        img = Image.fromarray(a.squeeze(-1) if a.ndim == 3 and a.shape[-1] == 1 else a)
    if img.mode not in ("RGB", "RGBA", "L"):
        img = img.convert("RGBA")
    if img.width > MAX_WIDTH:
        img = img.resize((MAX_WIDTH, max(1, round(img.height * MAX_WIDTH / img.width))),
                         Image.LANCZOS)
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=True)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _figure_uri(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    import matplotlib.pyplot as plt
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.3e}"
    return html.escape(str(v))


def _table(header: list, rows: list) -> str:
    th = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def _img(uri: str, caption: str) -> str:
    c = html.escape(caption)
    return f'<figure><img src="{uri}" alt="{c}"><figcaption>{c}</figcaption></figure>'


# ----------------------------------------------------------------------------- plots

def load_logs(run_dir) -> dict[str, list[dict]]:
    """{"<relative folder>: <stage>": records} of every ``*metrics.jsonl`` below ``run_dir``."""
    run_dir = Path(run_dir)
    out: dict[str, list[dict]] = {}
    for p in sorted(run_dir.rglob(f"*{runlog.LOG_NAME}")):
        rel = p.parent.relative_to(run_dir).as_posix()
        for r in runlog.read_records(p):
            key = f"{r['stage']}" + (f"  ({rel})" if rel != "." else "")
            out.setdefault(key, []).append(r)
    return dict(sorted(out.items(), key=lambda kv: (_stage_rank(kv[0]), kv[0])))


_ORDER = ("demo", "reconstruct", "decompose", "train-completion", "estimate-light", "compose",
          "render-comp")


def _stage_rank(key: str) -> int:
    """Pipeline order of a log key (unknown stages last)."""
    return next((i for i, s in enumerate(_ORDER) if key.startswith(s)), len(_ORDER))


def plot_logs(logs: dict[str, list[dict]]) -> str | None:
    """One matplotlib panel per stage: PSNR (or loss, log scale) against wall time; stages
    made of named parts (compose, estimate-light, the demo) as a timeline of parts."""
    if not logs:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n = len(logs)
    cols = min(3, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.2 * rows), squeeze=False)
    for ax, (name, recs) in zip(axes.ravel(), logs.items()):
        ax.set_title(name, fontsize=9)
        ax.grid(alpha=0.3)
        t = np.array([r["time_s"] for r in recs], float)
        keys = [k for k in _PSNR_KEYS if any(isinstance(r.get(k), (int, float)) for r in recs)]
        lkeys = [k for k in _LOSS_KEYS if any(isinstance(r.get(k), (int, float)) for r in recs)]
        if keys:
            for k in keys:
                pts = [(r["time_s"], r[k]) for r in recs if isinstance(r.get(k), (int, float))]
                style = "o-" if k in ("psnr_test", "psnr") else "."
                ax.plot(*zip(*pts), style, ms=3 if style == "." else 4,
                        alpha=0.5 if style == "." else 1.0, label=k)
            ax.set_ylabel("PSNR [dB] (higher is better)")
            ax.legend(fontsize=7)
        elif lkeys:
            for k in lkeys:
                pts = [(r["time_s"], r[k]) for r in recs if isinstance(r.get(k), (int, float))
                       and r[k] > 0]
                if pts:
                    ax.plot(*zip(*pts), "-", label=k)
            ax.set_yscale("log")
            ax.set_ylabel("loss (lower is better)")
            ax.legend(fontsize=7)
        elif any("part" in r for r in recs):
            parts = [(r.get("part", "?"), float(r.get("part_s", 0.0)), r["time_s"]) for r in recs]
            for i, (p, d, end) in enumerate(parts):
                ax.barh(i, d, left=end - d, color=f"C{i % 10}")
                ax.text(end, i, f" {d:.1f} s", va="center", fontsize=7)
            ax.set_yticks(range(len(parts)), [p for p, _, _ in parts], fontsize=7)
            ax.invert_yaxis()
            ax.set_xlim(0, max(t.max() * 1.25, 1e-3))
        ax.set_xlabel("wall time [s]")
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.tight_layout()
    return _figure_uri(fig)


# ----------------------------------------------------------------------------- sections

def _demo_section(d: dict) -> str:
    s = ["<h2>Composition against path-traced ground truth</h2>"]
    comp = d.get("composition", {})
    if comp:
        s.append(_table(["variant", "PSNR [dB]", "SSIM", "s / frame"],
                        [[v, m["psnr"], m["ssim"], m["frame_seconds"]] for v, m in comp.items()]))
        s.append(f"<p>SOP composition better than the naive paste on "
                 f"{d.get('sop_beats_paste_frames')}/{d.get('frames')} frames.</p>")
    reg = {v: r for v, r in (d.get("region") or {}).items() if r}
    if reg:
        first = next(iter(reg.values()))
        s += ["<h3>Where the object was inserted (the object + the truth's shadow)</h3>",
              _table(["variant", "PSNR in the region [dB]", "shadow: ours / empty",
                      "truth / empty", "shadow depth vs truth", "depth over the area",
                      "object colour / truth (R, G, B)"],
                     [[v, r.get("psnr_region"), r.get("shadow_ratio"),
                       r.get("shadow_ratio_truth"), r.get("shadow_depth"),
                       r.get("shadow_depth_area"),
                       ", ".join(f"{c:.2f}" for c in r.get("object_colour_ratio", []))]
                      for v, r in reg.items()]),
              f"<p>Shadow pixels: the {first.get('shadow_pixels', 0)} pixels (pooled over "
              f"frames) where the truth is darker than 0.7 × its empty scene; depth "
              f"(1 − ours) / (1 − truth): 1 is as dark as the truth, from the per-pixel "
              f"mean of render / empty, and over the area (Σ render / Σ empty; a "
              f"reconstruction's blurred texture raises the per-pixel mean). SOP better than the paste in the region on "
              f"{d.get('sop_beats_paste_frames_region')}/{d.get('frames')} frames.</p>"]
    L = d.get("lighting")
    if L:
        rows = [[f"spheres {m}: si-RMSE", v["si_rmse"]] for m, v in L["spheres"].items()]
        rows += [[f"spheres {m}: angular error [deg]", v["angular_deg"]]
                 for m, v in L["spheres"].items()]
        for k in ("light_angle_deg", "light_up_irradiance_ratio_est",
                  "light_up_irradiance_ratio_gt", "power_ratio_est_gt"):
            if L.get(k) is not None:
                rows.append([k, L[k]])
        Lm = d.get("lighting_vs_map") or {}
        for k in ("light_angle_deg", "light_up_irradiance_ratio_gt"):
            if Lm.get(k) is not None:
                rows.append([f"{k} (against the scene's map instead)", Lm[k]])
        truth = ("the true light there (the scene without the object, path-traced from the "
                 "placement)" if "lighting_vs_map" in d else "the scene's map")
        s += [f"<h3>Lighting estimated at the placement vs {truth}</h3>",
              _table(["measure", "value"], rows)]
    st = d.get("stage_seconds", {})
    if st:
        s += ["<h3>Stage times</h3>",
              _table(["stage", "seconds"], [[k, v] for k, v in st.items()]
                     + [["total", d.get("total_seconds", sum(st.values()))]])]
    q = {k: d[k] for k in ("scene_step1_psnr_test", "object_step1_psnr_test",
                           "object_step2_psnr_test") if k in d}
    if q:
        s += ["<h3>Reconstruction (test views)</h3>",
              _table(["measure", "PSNR [dB]"], [[k, v] for k, v in q.items()])]
    return "\n".join(s)


def _summaries(run_dir: Path) -> str:
    s = []
    rows = []
    for p in sorted(run_dir.rglob("train_log.json")):
        summ = (json.loads(p.read_text()).get("summary") or {})
        rows.append([p.parent.relative_to(run_dir).as_posix() or ".", summ.get("iterations"),
                     summ.get("train_seconds"), summ.get("psnr_test"), summ.get("ssim_test", "")])
    if rows:
        s += ["<h2>Training runs</h2>",
              _table(["run", "iterations", "train s", "test PSNR", "test SSIM"], rows)]
    rows = []
    for p in sorted(run_dir.rglob("metrics_*.json")):
        m = json.loads(p.read_text())
        rows.append([p.relative_to(run_dir).as_posix(), m.get("psnr"), m.get("ssim"),
                     m.get("frame_seconds", ""), m.get("frames", m.get("views", ""))])
    if rows:
        s += ["<h2>Rendered metrics</h2>",
              _table(["file", "PSNR", "SSIM", "s / frame", "frames"], rows)]
    for p in sorted(run_dir.rglob("edit.json")):
        e = json.loads(p.read_text())
        s += [f"<h2>Edit stage ({html.escape(p.parent.relative_to(run_dir).as_posix() or '.')})</h2>",
              _table(["part", "seconds"], [[k, v] for k, v in e.get("timings", {}).items()])]
        if e.get("exposure"):          # data.exposure: the object -> scene gain of each object
            s += [_table(["object", "exposure gain (R, G, B)", "EV", "method", "assumed"],
                         [[n, ", ".join(f"{v:.3f}" for v in x.get("gain", [])),
                           x.get("exposure_ev"), x.get("method"), x.get("assumed")]
                          for n, x in e["exposure"].items()])]
    for p in sorted(run_dir.rglob("*.json")):
        if p.name.endswith(".json") and p.with_name(p.stem + "_preview.png").is_file():
            e = json.loads(p.read_text())
            meta = e.get("meta", {})
            s += [f"<h2>Lighting estimate {html.escape(p.stem)}</h2>",
                  _table(["field", "value"],
                         [["coverage", meta.get("coverage")], ["backend", meta.get("backend")],
                          ["position", meta.get("position")],
                          ["sun from the scene's shadows",
                           (meta.get("sun_from_shadows") or {}).get("action", "off")]]
                         + [[f"{k} s", v] for k, v in e.get("timings", {}).items()])]
    return "\n".join(s)


def _paths(run_dir: Path) -> str:
    """Camera-path renders (``render-comp --path``: ``path_<variant>.json``): a table, the
    first frame and a link to the video, relative to the report when it lies inside the
    folder."""
    s = []
    for p in sorted(run_dir.rglob("path_*.json")):
        m = json.loads(p.read_text())
        renders = Path(m.get("renders", p.parent / "renders" / m.get("variant", "")))
        first = sorted(renders.glob("path_*.png"))[:1] if renders.is_dir() else []
        video = m.get("video")
        s += [f"<h2>Camera path {html.escape(p.stem[5:])} "
              f"({html.escape(p.parent.relative_to(run_dir).as_posix() or '.')})</h2>",
              _table(["path", "frames", "s / frame", "resolution", "video", "KiB"],
                     [[m.get("path"), len(m.get("per_frame", [])) or m.get("frames"),
                       m.get("frame_seconds"), m.get("resolution"), video,
                       round(m["video_bytes"] / 1024, 1) if "video_bytes" in m else ""]])]
        if first:
            s.append(_img(png_data_uri(first[0]), "the path's first frame"))
        if video:
            v = Path(video)
            href = os.path.relpath(v, run_dir) if v.is_absolute() else v.as_posix()
            s.append(f"<p><a href='{html.escape(Path(href).as_posix())}'>the video "
                     f"({html.escape(v.name)})</a></p>")
    return "\n".join(s)


def _pictures(run_dir: Path, limit: int = 4) -> list[tuple[str, str]]:
    """[(caption, data uri)] of the folder's known pictures."""
    pics = []
    for name, cap in (("comparison.png", "ground truth | ours (SOP) | ours (trace) | naive paste"),
                      ("crops.png", "full size, the frame with the most shadow: the shadow "
                                    "and the object, truth | ours (SOP) | ours (trace) | paste"),
                      ("shadow_profile.png", "the shadow's darkness along its axis: each "
                                             "image's luminance over the truth's empty scene"),
                      ("envmaps.png", "environment map: true | estimated at the placement")):
        for p in sorted(run_dir.rglob(name)):
            pics.append((cap, png_data_uri(p)))
    for p in sorted(run_dir.rglob("*_preview.png")):
        pics.append((f"lighting estimate {p.stem}", png_data_uri(p)))
    if not any(c.startswith("ground truth") for c, _ in pics):
        for d in sorted(run_dir.rglob("renders/*")) + sorted(run_dir.rglob("render_*")):
            if d.is_dir():
                frames = sorted(d.glob("*.png"))[:limit]
                if frames:
                    ims = [np.asarray(Image.open(f).convert("RGB")) for f in frames]
                    h = min(i.shape[0] for i in ims)
                    strip = np.concatenate([i[:h] for i in ims], 1)
                    pics.append((f"{d.relative_to(run_dir).as_posix()}: first {len(ims)} frames",
                                 png_data_uri(strip)))
    return pics


_CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1500px;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.2em}td,th{border:1px solid #ccc;padding:3px 8px;
text-align:right}th{background:#f0f0f0}td:first-child{text-align:left}
figure{margin:0 0 1.5em}img{max-width:100%;image-rendering:pixelated}
figcaption{color:#555;font-size:90%}"""


def build_report(run_dir, title: str | None = None) -> str:
    """The HTML text of the report of ``run_dir`` (see the module docstring)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"comgs report: {run_dir} is not a folder")
    logs = load_logs(run_dir)
    demo = run_dir / "demo.json"
    parts = [f"<h1>{html.escape(title or f'comgs report: {run_dir.name}')}</h1>",
             f"<p>{html.escape(str(run_dir.resolve()))} &middot; "
             f"{time.strftime('%Y-%m-%d %H:%M')}</p>"]
    pics = _pictures(run_dir)
    if demo.is_file():
        parts.append(_demo_section(json.loads(demo.read_text())))
    for cap, uri in pics:
        parts.append(_img(uri, cap))
    plot = plot_logs(logs)
    if plot:
        parts += ["<h2>Error against run time, every stage</h2>",
                  _img(plot, "each stage's metrics.jsonl: PSNR or loss against wall time; "
                             "part timelines for stages without an error measure")]
    summaries = _summaries(run_dir) + _paths(run_dir)
    parts.append(summaries)
    if not logs and not pics and not summaries and not demo.is_file():
        raise FileNotFoundError(f"comgs report: nothing to report in {run_dir} (no "
                                f"metrics.jsonl, summaries or pictures of a comgs stage)")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>"
            f"{html.escape(title or run_dir.name)}</title><style>{_CSS}</style></head><body>"
            + "\n".join(parts) + "</body></html>")


def write_report(run_dir, out=None, title: str | None = None) -> Path:
    """Write :func:`build_report` to ``out`` (default ``RUN_DIR/report.html``)."""
    out = Path(out) if out is not None else Path(run_dir) / "report.html"
    text = build_report(run_dir, title)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(out)
    return out
