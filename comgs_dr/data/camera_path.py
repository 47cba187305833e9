"""Camera paths of ``comgs render-comp --path``: frames that are not capture views.

``orbit``: N cameras on a circle around a centre (the placed objects' centre), at the
capture cameras' mean distance to it and mean elevation above it (world +Z up, the
reconstruction frame), evenly spaced in azimuth over one turn starting at the first
capture camera's azimuth, each looking at the centre (+Z up). ``spiral``: the orbit with
the elevation swinging twice per turn (±max(half the capture's elevation spread, 5°)) and
the distance once (±max(half its relative spread, 10 %)), like LLFF's spiral render path
but around the objects. A file: a NeRF ``transforms.json`` of cameras
(``comp_folder.read_cameras``). Every path frame is named ``path_0000``, ``path_0001``, …
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from comgs_dr.data import comp_folder

SHAPES = ("orbit", "spiral")
MAX_FRAMES = 100_000
#: elevations stay within ±this (degrees): a camera straight above the centre has no roll
MAX_ELEVATION_DEG = 85.0


def frame_name(i: int) -> str:
    return f"path_{i:04d}"


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Mitsuba camera-to-world [4, 4] (+X left, +Y up, +Z forward) from ``eye`` to
    ``target`` (ValueError when they coincide or the view runs along ``up``)."""
    e, t, u = (np.asarray(v, np.float64).reshape(3) for v in (eye, target, up))
    f = t - e
    if not np.isfinite(f).all() or np.linalg.norm(f) <= 0:
        raise ValueError(f"look_at: eye {e.tolist()} and target {t.tolist()} must be finite "
                         f"and distinct")
    f = f / np.linalg.norm(f)
    left = np.cross(u, f)
    if np.linalg.norm(left) < 1e-9:
        raise ValueError(f"look_at: the view direction {f.tolist()} runs along up {u.tolist()}")
    left /= np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(f, left), f, e
    return m


def axes_centre(cams: list[dict]) -> np.ndarray:
    """The point nearest every camera's optical axis (least squares): what a capture looks
    at, the centre of a path when the composition places no object."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cams:
        m = np.asarray(c["to_world"], np.float64)
        d = m[:3, 2] / np.linalg.norm(m[:3, 2])
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ m[:3, 3]
    if np.linalg.matrix_rank(A, 1e-9) < 3:          # parallel axes: a point ahead of them
        return np.mean([np.asarray(c["to_world"])[:3, 3] + np.asarray(c["to_world"])[:3, 2]
                        for c in cams], 0)
    return np.linalg.solve(A, b)


def objects_centre(manifest: dict) -> np.ndarray | None:
    """Centre of the placed objects' bounds (their mean, as ``comp_folder.clip_for``), or
    None when the composition places none."""
    b = np.array([o["bounds"] for o in manifest["objects"].values()], np.float64)
    return b.reshape(-1, 2, 3).mean((0, 1)) if len(b) else None


def capture_geometry(centre, capture: list[dict]) -> dict:
    """Distance, elevation (degrees) and azimuth (radians) of the capture cameras around
    ``centre``: their means and spreads, what :func:`poses` places the path by."""
    c = np.asarray(centre, np.float64)
    rel = np.array([np.asarray(k["to_world"], np.float64)[:3, 3] - c for k in capture])
    dist = np.linalg.norm(rel, axis=1)
    if not len(rel) or not np.all(dist > 0):
        raise ValueError("camera path: a capture camera sits at the path's centre")
    elev = np.degrees(np.arcsin(np.clip(rel[:, 2] / dist, -1.0, 1.0)))
    p10, p90 = np.percentile(elev, [10, 90])
    d10, d90 = np.percentile(dist, [10, 90])
    return {"distance": float(dist.mean()), "elevation_deg": float(elev.mean()),
            "azimuth0": float(np.arctan2(rel[0, 1], rel[0, 0])),
            "elevation_spread_deg": float(p90 - p10),
            "distance_spread": float((d90 - d10) / dist.mean())}


def poses(shape: str, n: int, centre, geometry: dict) -> list[np.ndarray]:
    """``n`` Mitsuba camera-to-worlds of an ``orbit`` or ``spiral`` (module docstring)."""
    if shape not in SHAPES:
        raise ValueError(f"camera path: shape must be one of {', '.join(SHAPES)} or a "
                         f"transforms.json, got {shape!r}")
    c = np.asarray(centre, np.float64)
    g = geometry
    t = np.arange(n) / n
    az = g["azimuth0"] + 2 * np.pi * t
    el = np.full(n, g["elevation_deg"])
    dist = np.full(n, g["distance"])
    if shape == "spiral":
        el = el + max(g["elevation_spread_deg"] / 2, 5.0) * np.sin(4 * np.pi * t)
        dist = dist * (1.0 + max(g["distance_spread"] / 2, 0.1) * np.cos(2 * np.pi * t))
    el = np.radians(np.clip(el, -MAX_ELEVATION_DEG, MAX_ELEVATION_DEG))
    eyes = c + dist[:, None] * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                         np.sin(el)], 1)
    return [look_at(e, c) for e in eyes]


def path_cameras(path, n: int | None, capture: list[dict], centre=None, res=None,
                 world_from_source=None) -> list[dict]:
    """Camera dicts (``comp_folder.camera``) of a path, named ``path_0000`` …

    ``path``: "orbit" or "spiral" (``n`` frames around ``centre``, default the point the
    capture looks at, placed by the ``capture`` cameras; intrinsics of ``capture[0]``,
    rescaled to ``res`` (int or (w, h)) when given), or a NeRF ``transforms.json``
    (its frames, in the scene dataset's frame: ``world_from_source``; ``n`` must be None
    or its frame count; size: ``res``, else the file's, else ``capture[0]``'s).
    ValueError naming the problem (and the file)."""
    if n is not None and (isinstance(n, bool) or int(n) != n or not 1 <= n <= MAX_FRAMES):
        raise ValueError(f"camera path: frames must be an integer in [1, {MAX_FRAMES}], "
                         f"got {n!r}")
    res_wh = None if res is None else (res, res) if isinstance(res, int) else tuple(res)
    if str(path) not in SHAPES:
        p = Path(path)
        if p.suffix.lower() != ".json":
            raise ValueError(f"camera path: {path!r} is neither orbit, spiral nor a "
                             f"transforms .json file")
        cams = comp_folder.read_cameras(p, world_from_source, res)
        if n is not None and n != len(cams):
            raise ValueError(f"camera path: {p} has {len(cams)} frames, --frames {n} asks "
                             f"for {n} (leave --frames out to render the file's)")
        out = []
        for i, c in enumerate(cams):
            if c["width"] is None:
                if not capture or capture[0]["width"] is None:
                    raise ValueError(f"camera path: {p}: image size unknown (no w/h in the "
                                     f"file): give --res")
                c = comp_folder.sized(c, capture[0]["width"], capture[0]["height"])
            c["name"] = frame_name(i)
            out.append(c)
        return out
    if not capture:
        raise ValueError("camera path: no capture cameras to place the path by")
    first = capture[0]
    if first["width"] is None and res_wh is None:
        raise ValueError("camera path: the capture cameras' image size is unknown: give --res")
    if res_wh is not None:
        first = comp_folder.sized(first, *res_wh)
    centre = axes_centre(capture) if centre is None else np.asarray(centre, np.float64)
    geo = capture_geometry(centre, capture)
    return [comp_folder.camera(frame_name(i), m, first["width"], first["height"], first["fx"],
                               first["fy"], first["cx"], first["cy"])
            for i, m in enumerate(poses(str(path), int(n or 60), centre, geo))]
