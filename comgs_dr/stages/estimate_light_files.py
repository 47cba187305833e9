"""Files of the lighting-estimation stage: the equirect and octahedral EXRs, the JSON of
meta, timings, lights and the light head's regions, and the labelled preview sheet
(``estimate_light.estimate_light``'s result in, paths out)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from comgs_dr.core import colorspace, runlog
from comgs_dr.core.equirect import equirect_dir_to_uv_np
from comgs_dr.data.images import to_u8
from comgs_dr.lighting import envmap
from comgs_dr.lighting import lights as light_head

__all__ = ["output_paths", "write_outputs", "preview_image", "jsonable", "sky_text",
           "summary_text"]


jsonable = runlog.json_safe          # numpy to Python, non-finite floats to None (strict JSON)


def _wrap(text: str, font, width: int) -> list[str]:
    """``text`` in lines of at most ``width`` pixels in ``font`` (split at spaces; a single
    word wider than that stays whole)."""
    lines = []
    for word in text.split(" "):
        if lines and font.getlength(lines[-1] + " " + word) <= width:
            lines[-1] += " " + word
        else:
            lines.append(word)
    return lines or [""]


def output_paths(out_path) -> dict:
    """{'equirect': X.exr, 'oct': X_oct.exr, 'json': X.json, 'preview': X_preview.png,
    'metrics': X.metrics.jsonl}."""
    p = Path(out_path)
    if p.suffix.lower() != ".exr":
        raise ValueError(f"estimate-light --out: the output must be an .exr file, got {p}")
    for d in p.parents:
        if d.exists() and not d.is_dir():
            raise ValueError(f"estimate-light --out: cannot write {p}: {d} is a file, not a folder")
    if p.is_dir():
        raise ValueError(f"estimate-light --out: {p} is a folder; give the .exr file to write")
    stem = p.with_suffix("")
    return {"equirect": p, "oct": Path(f"{stem}_oct.exr"), "json": Path(f"{stem}.json"),
            "preview": Path(f"{stem}_preview.png"), "metrics": Path(f"{stem}.{runlog.LOG_NAME}")}


def write_outputs(result: dict, out_path) -> dict:
    """Write the equirect HDR (``out_path``, EXR with layout metadata), the octahedral map
    (``*_oct.exr``), ``*.json`` (meta, timings, lights, file names) and a labelled
    ``*_preview.png``. Returns the paths (``output_paths``)."""
    paths = output_paths(out_path)
    envmap.write_exr(paths["equirect"], result["hdr"], "equirect")
    envmap.write_exr(paths["oct"], result["oct"], "octahedral")
    doc = {"meta": result["meta"], "timings": result["timings"], "lights": result["lights"],
           "lobes": result.get("lobes", []),
           "light_head_regions": [{k: v for k, v in g.items() if k != "region"}
                                  for g in result.get("light_regions", [])],
           "files": {k: v.name for k, v in paths.items()}}                # jsonable: lists
    paths["json"].write_text(json.dumps(jsonable(doc), indent=2, allow_nan=False))
    runlog.rewrite(paths["metrics"].parent,
                   runlog.part_records("estimate-light", result["timings"],
                                       coverage=float(result["coverage"])),
                   name=paths["metrics"].name)
    preview_image(result).save(paths["preview"])
    return paths


def sky_text(meta: dict) -> str:
    """"upper hemisphere seen X% [(open sky Z%)], of it clipped Y%" when the meta holds
    them, else "" (the preview's mask title and ``estimate-light``'s printout).
    ``seen_sky_fraction`` counts whatever is observed above the horizon (a wall, a ceiling,
    floaters); ``open_sky_fraction``, when step 1 learned a background, the share of it
    that is that background (the sky itself)."""
    if meta.get("seen_sky_fraction") is None or meta.get("clipped_sky_fraction") is None:
        return ""
    sky = meta.get("open_sky_fraction")
    sky = "" if sky is None else f" (open sky {100 * sky:.1f}%)"
    return (f"upper hemisphere seen {100 * meta['seen_sky_fraction']:.1f}%{sky}, of it "
            f"clipped {100 * meta['clipped_sky_fraction']:.1f}%")   # as the warnings print them


def summary_text(result: dict, paths: dict) -> str:
    """What ``comgs estimate-light`` prints of a result and its written ``paths``: coverage,
    backend and lights, the sky (:func:`sky_text`), the classifier's label, what the light
    head did in each clipped region, the dominance of the strongest light, the timings."""
    meta = result["meta"]
    hot = sum(bool(l.get("above_white")) for l in result["lights"])
    lines = [f"coverage {100 * result['coverage']:.1f}%, backend {meta['backend']}, "
             f"{len(result['lights'])} brightest region(s), {hot} of them above the EV-0 white "
             f"level (lights), peak radiance {float(result['hdr'].max()):.3g}",
             sky_text(meta)]
    if meta.get("p_outdoor") is not None:
        lines.append(f"label auto -> {meta['label']} (p(outdoor) {meta['p_outdoor']:.2f})")
    for i, g in enumerate(result.get("light_regions", [])):     # what the light head did
        el = float(np.degrees(np.arcsin(np.clip(g["direction"][2], -1.0, 1.0))))
        lines.append(f"clipped region {i}: {g['solid_angle']:.4g} sr at elevation {el:+.1f}°, "
                     f"gain {g['gain']:.3g}, power {g['predicted_power']:.3g} (after the "
                     f"brackets' vote {g['voted_power']:.3g}), map {g['brackets_power']:.3g} "
                     f"-> {g['power']:.3g} ({g['action']})")
    dom = meta.get("light_dominance")
    if dom is not None:
        lines.append(f"strongest observed clipped light: {dom:.2f}x the next"
                     + (" (a near tie: see light_head_regions in the JSON)"
                        if dom < light_head.DOMINANCE_MARGIN else ""))
    lines.append(f"{'step':<12}{'seconds':>10}")
    lines += [f"{k:<12}{v:>10.3f}" for k, v in result["timings"].items()]
    lines.append("wrote " + ", ".join(str(p) for p in paths.values()))
    return "\n".join(lines)


def preview_image(result: dict, panel_width: int = 512):
    """PIL image: labelled panels (input LDR, mask, normal, completion per EV, fused HDR
    tone-mapped by ``colorspace.tonemap``: Reinhard on luminance, and, when the light head
    ran, the clipped regions it read over the dimmed input: orange where it added power, cyan
    where it reduced the brackets' excess, grey where it left them, each labelled with its
    gain), two per row, each at most ``panel_width`` wide."""
    inp = result["input"]
    mask = inp["mask"]
    meta = result["meta"]
    lab = meta.get("label", "?")
    if meta.get("p_outdoor") is not None:
        lab = f"{lab} (auto, p(outdoor) {meta['p_outdoor']:.2f})"
    panels = [(f"traced input LDR (EV 0), label {lab}", inp["rgb"]),
              (f"mask (coverage {100 * result['coverage']:.1f}%"
               f"{', ' + sky_text(meta) if sky_text(meta) else ''})",
               np.repeat(mask[..., None], 3, -1)),
              ("normal (n/2 + 1/2)", np.where(mask[..., None] > 0, inp["normal"] * 0.5 + 0.5, 0))]
    for ev in sorted(result["ldrs"], reverse=True):
        panels.append((f"completion EV {ev:g}", result["ldrs"][ev]))
    h = result["hdr"]
    panels.append((f"fused HDR, Reinhard (max {float(h.max()):.3g})",
                   colorspace.tonemap(h)))
    regions, at = result.get("light_regions"), -1
    if result["meta"].get("light_head") is not None and regions is not None:
        n = {a: sum(g["action"] == a for g in regions) for a in ("added", "reduced")}
        at = len(panels)
        panels.append((f"light head: {len(regions)} clipped region(s); added "
                       f"{n['added']} (orange), reduced {n['reduced']} (cyan)",
                       light_head.regions_overlay(inp["rgb"], regions)))
    font = ImageFont.load_default()
    ih, iw = panels[0][1].shape[:2]
    pw = min(panel_width, iw)
    titles = [_wrap(t, font, pw - 8) for t, _ in panels]        # no title runs into the next
    ph, bar, cols = max(1, round(ih * pw / iw)), 4 + 12 * max(len(t) for t in titles), 2
    rows = -(-len(panels) // cols)
    sheet = Image.new("RGB", (cols * pw, rows * (ph + bar)), (32, 32, 32))
    draw = ImageDraw.Draw(sheet)
    for i, (_, img) in enumerate(panels):
        x, y = (i % cols) * pw, (i // cols) * (ph + bar)
        tile = Image.fromarray(to_u8(img)).resize((pw, ph), Image.BILINEAR)
        sheet.paste(tile, (x, y + bar))
        for k, line in enumerate(titles[i]):
            draw.text((x + 4, y + 2 + 12 * k), line, fill=(255, 255, 255), font=font)
        if i == at:                                            # gains at the regions
            for g in regions:
                u, v = equirect_dir_to_uv_np(np.asarray(g["direction"])[None])[0]
                draw.text((x + min(int(u * pw), pw - 40), y + bar + min(int(v * ph), ph - 12)),
                          f"x{g['gain']:.3g}", fill=(255, 255, 255), font=font)
    return sheet
