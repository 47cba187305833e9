"""A composition folder (``comgs compose`` → ``comgs render-comp``): its manifest, the
Mitsuba scene it describes, and its cameras (NeRF transforms files, dataset folders) with
full pinhole intrinsics.

``COMP_DIR/composition.json``::

    {"version": 1, "scene": {"run", "ply", "colour_space"},
     "world_from_source": 4×4 (the scene dataset's frame → the reconstruction's),
     "objects": {name: {"run", "ply", "placement": 4×4 object→world (reconstruction frame),
                        "envmap": "env/<name>.exr", "probes": "probes/<name>.npz",
                        "bounds": [lo, hi]}},
     "shadow_probes": "shadow_probes.npz", "config": {...}}

Paths inside the folder are relative to it; run paths are absolute. ``composition.xml`` is
the same scene as Mitsuba XML (``comgs_composite`` + surfels shapes), for use outside the CLI.
"""
from __future__ import annotations

import json
from pathlib import Path
from xml.sax.saxutils import quoteattr

import mitsuba as mi
import numpy as np

from comgs_dr.core.cameras import pinhole
from comgs_dr.data.types import clip_planes

MANIFEST = "composition.json"
FORMAT_VERSION = 1
GL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])     # OpenGL camera axes → Mitsuba's


def read_manifest(comp_dir) -> dict:
    p = Path(comp_dir) / MANIFEST
    if not p.is_file():
        raise FileNotFoundError(f"{p} not found: is {comp_dir} a `comgs compose` folder?")
    m = _read_json(p)
    version = m.get("version", 0)
    if not isinstance(version, int) or isinstance(version, bool):
        raise ValueError(f"{p}: 'version' must be an integer, got {version!r:.40}")
    if version > FORMAT_VERSION:
        raise ValueError(f"{p}: format version {m['version']}, this comgs_dr reads "
                         f"≤ {FORMAT_VERSION}")
    _check_manifest(p, m)
    return m


def _read_json(p: Path) -> dict:
    try:
        d = json.loads(p.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{p}: not valid UTF-8 JSON ({e})") from None
    if not isinstance(d, dict):
        raise ValueError(f"{p}: expected a JSON object, got {type(d).__name__}")
    return d


def _check_manifest(p: Path, m: dict) -> None:
    """The fields the renderer reads, with their types (ValueError naming the file)."""
    def matrix(v, what):
        try:
            a = np.asarray(v, np.float64)
        except (TypeError, ValueError, OverflowError):
            a = None
        if a is None or a.shape != (4, 4) or not np.isfinite(a).all():
            raise ValueError(f"{p}: {what} must be a finite 4x4 matrix, got {v!r:.80}")

    scene, objects = m.get("scene"), m.get("objects")
    if not isinstance(scene, dict) or not isinstance(scene.get("ply"), str):
        raise ValueError(f"{p}: 'scene' must be an object with a 'ply' path")
    if "colour_space" in scene and scene["colour_space"] not in ("srgb", "linear"):
        raise ValueError(f"{p}: scene 'colour_space' must be 'srgb' or 'linear', got "
                         f"{scene['colour_space']!r:.40}")
    if not isinstance(objects, dict):
        raise ValueError(f"{p}: 'objects' must be an object {{name: ...}}")
    if not isinstance(m.get("shadow_probes", ""), str):
        raise ValueError(f"{p}: 'shadow_probes' must be a path")
    if "world_from_source" in m:
        matrix(m["world_from_source"], "'world_from_source'")
    for name, o in objects.items():
        if not isinstance(o, dict):
            raise ValueError(f"{p}: object {name!r} must be an object")
        missing = [k for k in ("ply", "envmap", "probes") if not isinstance(o.get(k), str)]
        if missing:
            raise ValueError(f"{p}: object {name!r} lacks path(s) {missing}")
        matrix(o.get("placement"), f"object {name!r} 'placement'")
        try:
            b = np.asarray(o.get("bounds"), np.float64)
        except (TypeError, ValueError, OverflowError):
            b = None
        if b is None or b.shape != (2, 3) or not np.isfinite(b).all():
            raise ValueError(f"{p}: object {name!r} 'bounds' must be [[x, y, z], [x, y, z]]")


def integrator_props(comp_dir, manifest: dict, variant: str = "sop",
                     materials: dict | None = None, relative: bool = False, **extra) -> dict:
    """Properties of the ``comgs_composite`` integrator for a composition folder; the
    folder's own files as absolute paths, or (``relative``) relative to it, as an XML file
    inside it needs them to stay valid when the folder is moved or copied."""
    root = Path("") if relative else Path(comp_dir).resolve()
    props = {"type": "comgs_composite", "variant": variant, "scene_shape": "scene",
             "colour_space": manifest["scene"].get("colour_space", "srgb")}
    if manifest["scene"].get("sky"):                 # step 1's learned sky (--background env)
        props["sky"] = str(manifest["scene"]["sky"])
    if variant in ("sop", "trace"):      # trace: the receivers' normals (shadow_normals)
        props["shadow_probes"] = str(root / manifest["shadow_probes"])
    for name, o in manifest["objects"].items():
        props[f"envmap_{name}"] = str(root / o["envmap"])
        if variant != "paste":
            props[f"probes_{name}"] = str(root / o["probes"])
    for name, spec in (materials or {}).items():
        if name not in manifest["objects"]:
            raise ValueError(f"material override for {name!r}: no such object "
                             f"(objects: {', '.join(manifest['objects'])})")
        props[f"material_{name}"] = spec
    props.update(extra)
    return props


def shape_dicts(manifest: dict) -> dict:
    """{id: surfels shape dict} of the scene and the placed objects."""
    out = {"scene": {"type": "surfels", "filename": manifest["scene"]["ply"]}}
    for name, o in manifest["objects"].items():
        out[name] = {"type": "surfels", "filename": o["ply"],
                     "to_world": mi.ScalarTransform4f(np.asarray(o["placement"]).tolist())}
    return out


def write_xml(path, comp_dir, manifest: dict, variant: str = "sop") -> Path:
    """``composition.xml``: the composition as a Mitsuba scene (one example sensor). Written
    inside ``comp_dir``, it names the folder's files relative to itself (Mitsuba resolves
    them against the XML's folder), so a copied or moved folder still renders its own."""
    inside = Path(path).resolve().parent == Path(comp_dir).resolve()     # the usual case
    props = integrator_props(comp_dir, manifest, variant, relative=inside)
    lines = ['<scene version="3.0.0">', '    <integrator type="comgs_composite">']
    for k, v in props.items():
        if k != "type":
            lines.append(f'        <string name="{k}" value={quoteattr(str(v))}/>')
    lines.append("    </integrator>")
    lines.append(f'    <shape type="surfels" id="scene"><string name="filename" '
                 f'value={quoteattr(manifest["scene"]["ply"])}/></shape>')
    for name, o in manifest["objects"].items():
        m = " ".join(f"{v:.9g}" for v in np.asarray(o["placement"]).ravel())
        lines.append(f'    <shape type="surfels" id={quoteattr(name)}>')
        lines.append(f'        <string name="filename" value={quoteattr(o["ply"])}/>')
        lines.append(f'        <transform name="to_world"><matrix value="{m}"/></transform>')
        lines.append("    </shape>")
    c = np.mean([np.add(*o["bounds"]) / 2 for o in manifest["objects"].values()], 0) \
        if manifest["objects"] else np.zeros(3)
    eye = c + np.array([3.0, -3.0, 2.0]) * max(
        [np.linalg.norm(np.subtract(o["bounds"][1], o["bounds"][0])) for o in
         manifest["objects"].values()] or [1.0])
    lines += ['    <sensor type="perspective" id="sensor">', '        <float name="fov" value="40"/>',
              '        <transform name="to_world"><lookat origin="{}" target="{}" up="0, 0, 1"/>'
              '</transform>'.format(", ".join(f"{v:.6g}" for v in eye),
                                    ", ".join(f"{v:.6g}" for v in c)),
              '        <film type="hdrfilm"><integer name="width" value="256"/>'
              '<integer name="height" value="256"/><rfilter type="box"/></film>',
              "    </sensor>", "</scene>"]
    p = Path(path)
    p.write_text("\n".join(lines) + "\n")
    return p


def camera(name: str, to_world, width: int | None, height: int | None, fx=None, fy=None,
           cx=None, cy=None, **extra) -> dict:
    """A camera dict: {'name', 'to_world' (Mitsuba camera-to-world, reconstruction frame),
    'width', 'height', 'fx', 'fy', 'cx', 'cy' (OpenCV/COLMAP pixel intrinsics of that
    size, corner-origin), 'fov_x_deg' (2 atan(W / 2fx), for what reads only that)}.
    ``width`` None: the size is not known yet (:func:`sized` sets it, the intrinsics
    following from ``extra['intrinsic_keys']``, a transforms file's keys)."""
    c = {"name": str(name), "to_world": np.asarray(to_world, np.float64), "width": width,
         "height": height, "fx": fx, "fy": fy, "cx": cx, "cy": cy, **extra}
    if width is not None:
        c["width"], c["height"] = int(width), int(height)
        c["fx"], c["fy"], c["cx"], c["cy"] = (float(v) for v in (fx, fy, cx, cy))
        c["fov_x_deg"] = float(np.degrees(2.0 * np.arctan(0.5 * c["width"] / c["fx"])))
    return c


def sized(cam: dict, width: int, height: int) -> dict:
    """``cam`` for a ``width`` × ``height`` image (a new dict). A camera of unknown size
    takes its transforms file's keys at that size (pixel keys are that image's pixels, as
    step 1 reads them). A sized one is rescaled: at the same aspect (within 1 %) each axis
    by its own factor (the image was resampled); at another aspect the horizontal field of
    view, the pixel aspect fy/fx and the principal point's relative place are kept."""
    w, h = int(width), int(height)
    if cam["width"] is None:
        from comgs_dr.data.nerf import _intrinsics
        keys = cam.get("intrinsic_keys")
        if keys is None:
            raise ValueError(f"camera {cam['name']}: image size unknown (give --res or --gt-dir)")
        fx, fy, cx, cy = _intrinsics(keys, cam.get("where", cam["name"]))(w, h)
    else:
        sx, sy = w / cam["width"], h / cam["height"]
        fx, cx, cy = cam["fx"] * sx, cam["cx"] * sx, cam["cy"] * sy
        fy = cam["fy"] * (sy if abs(sx - sy) <= 0.01 * max(sx, sy) else sx)
    _check_intrinsics(cam.get("where", f"camera {cam['name']}"), fx, fy, cx, cy, w)
    extra = {k: v for k, v in cam.items() if k not in _CAMERA_KEYS + ("intrinsic_keys",)}
    return camera(cam["name"], cam["to_world"], w, h, fx, fy, cx, cy, **extra)


_CAMERA_KEYS = ("name", "to_world", "width", "height", "fx", "fy", "cx", "cy", "fov_x_deg")


def _check_intrinsics(where, fx, fy, cx, cy, w) -> None:
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise ValueError(f"{where}: invalid intrinsics fx={fx}, fy={fy}, cx={cx}, cy={cy} "
                         f"(focal lengths must be positive and finite)")
    if not 2.0 * np.degrees(np.arctan(0.5 * w / fx)) > 1e-6:
        raise ValueError(f"{where}: focal length fx={fx:.4g} px gives no field of view for a "
                         f"{w} px wide image")


def read_cameras(path, world_from_source=None, res=None) -> list[dict]:
    """Frames of a NeRF ``transforms*.json`` as :func:`camera` dicts (reconstruction frame).
    Intrinsics as step 1 reads them (``data.nerf``): ``camera_angle_x`` (and
    ``camera_angle_y``) or ``fl_x``/``fl_y``/``cx``/``cy`` in pixels of a ``w`` × ``h``
    image, top-level or per frame (a frame's keys win); non-zero distortion refused.
    Image size: ``res`` (int or (w, h); the intrinsics rescaled, :func:`sized`), else the
    file's ``w``/``h``, else unknown until the ground truth gives it. ValueError naming the
    file and frame for what cannot be read."""
    from comgs_dr.data.nerf import _DISTORTION_KEYS, _INTRINSIC_KEYS, _intrinsics
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"camera file not found: {p}")
    d = _read_json(p)
    frames = d.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{p}: not a NeRF camera file: 'frames' must be a non-empty list")
    W = np.eye(4) if world_from_source is None else np.asarray(world_from_source, np.float64)
    res_wh = None if res is None else (res, res) if isinstance(res, int) else tuple(res)
    keys = _INTRINSIC_KEYS + _DISTORTION_KEYS
    top = {k: d[k] for k in keys if k in d}
    out = []
    for i, f in enumerate(frames):
        if not isinstance(f, dict):
            raise ValueError(f"{p}: frame {i} must be an object")
        try:
            m = np.asarray(f["transform_matrix"], np.float64).reshape(4, 4)
            name = Path(str(f["file_path"])).name
        except (KeyError, TypeError, ValueError, OverflowError) as e:
            raise ValueError(f"{p}: frame {i} needs file_path and a 4×4 transform_matrix "
                             f"({e!r:.80})") from None
        where = f"{p}: frame {i} ({name})"
        if not np.all(np.isfinite(m)):
            raise ValueError(f"{where} has a non-finite transform_matrix")
        c = {**top, **{k: f[k] for k in keys if k in f}}
        at = _intrinsics(c, where)                  # DatasetError (a ValueError) on bad keys
        for k in ("w", "h"):
            if k in c and (isinstance(c[k], bool) or float(c[k]) != int(float(c[k]))):
                raise ValueError(f"{where}: '{k}' must be a positive integer, got {c[k]!r:.20}")
        cam = camera(name, W @ m @ GL_TO_MITSUBA, None, None, intrinsic_keys=c, where=where)
        if "w" in c and "h" in c:
            cam = sized(cam, int(float(c["w"])), int(float(c["h"])))
        else:
            _check_intrinsics(where, *at(1000, 1000), 1000)     # early: a nominal size
            cam["fov_x_deg"] = float(np.degrees(c["camera_angle_x"])) \
                if "camera_angle_x" in c else None
        out.append(sized(cam, *res_wh) if res_wh else cam)
    return out


def dataset_cameras(path, res=None, world_from_source=None) -> list[dict]:
    """Cameras of a captured dataset, as :func:`camera` dicts: the test views of a folder
    the loaders read (NeRF-synthetic, COLMAP, LLFF; or its ``poses_bounds.npy`` /
    transforms file), every view when it holds no test split. They are loaded as step 1
    loads them, so they are already in the reconstruction's frame (no
    ``world_from_source``), with each image's own intrinsics: focal length and principal
    point (COLMAP's cx, cy; a NeRF frame's; LLFF's centre), at the image's size (``res``:
    int or (w, h), rescaled as :func:`sized` does), fy as calibrated (step 1's loaders
    accept fx, fy within 1 % of each other and step 1 renders with fx; these keep both).
    ``world_from_source`` (the composition's): ValueError when the dataset's differs, i.e.
    the folder is not the one the scene was reconstructed from. Frame names are the views'
    file names without extension (as :func:`read_cameras` names a transforms file's frames),
    or, when two coincide (``cam0/0001.jpg``, ``cam1/0001.jpg``), their paths with "/" as "_".
    Only the images' headers are read (their sizes), not their pixels."""
    from comgs_dr.data.load import load_dataset
    data = load_dataset(path, pixels=False)
    if world_from_source is not None and not np.allclose(
            np.asarray(data.world_from_source, np.float64),
            np.asarray(world_from_source, np.float64), atol=1e-6):
        raise ValueError(f"{path}: this dataset's frame (its world_from_source) is not the "
                         f"composition's: it is not the dataset the scene was reconstructed "
                         f"from; give that one, or a transforms.json in its frame")
    views = data.test or data.train
    res_wh = None if res is None else (res, res) if isinstance(res, int) else tuple(res)
    out = []
    for v in views:
        c = v.camera
        fy = c.fx * float(getattr(c, "fy_over_fx", 1.0))         # as calibrated
        cam = camera(str(v.name), c.to_world, c.width, c.height, c.fx, fy, c.cx, c.cy)
        out.append(sized(cam, *res_wh) if res_wh else cam)
    from comgs_dr.data.images import IMAGE_EXTENSIONS
    strip = lambda n: str(Path(n).with_suffix("")) \
        if Path(n).suffix.lower() in IMAGE_EXTENSIONS else n                     # noqa: E731
    base = [Path(strip(c["name"])).name for c in out]
    full = [strip(c["name"]).replace("\\", "/").replace("/", "_") for c in out]
    names = base if len(set(base)) == len(base) else full
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"{path}: views share a name ({dup[:3]}): frames would overwrite "
                         f"each other")
    for c, n in zip(out, names):
        c["name"] = n
    return out


def camera_source(path, world_from_source=None, res=None) -> list[dict]:
    """``render-comp --cameras``: a NeRF ``transforms*.json`` (:func:`read_cameras`,
    in the scene dataset's frame) or a dataset folder / ``poses_bounds.npy``
    (:func:`dataset_cameras`). A folder holding a ``transforms_test.json`` but no training
    split (``make-dataset composition``'s ``comp/``) means that camera file."""
    p = Path(path)
    if p.suffix.lower() == ".json":
        return read_cameras(p, world_from_source, res)
    if not p.exists():
        raise FileNotFoundError(f"camera file or dataset folder not found: {p}")
    if p.is_dir() and (p / "transforms_test.json").is_file() \
            and not (p / "transforms_train.json").is_file():
        return read_cameras(p / "transforms_test.json", world_from_source, res)
    return dataset_cameras(p, res, world_from_source)


def sensor_dict(cam: dict, pixel_format: str = "rgb", clip: dict | None = None) -> dict:
    """Sensor reproducing a :func:`camera` dict's pinhole (``core.cameras.pinhole``:
    Mitsuba's ``perspective`` with its principal point offsets, or ``comgs_pinhole`` when
    fx ≠ fy); ``clip``: near/far planes (:func:`clip_for`)."""
    if cam["width"] is None:
        raise ValueError(f"camera {cam['name']}: image size unknown (give --res or --gt-dir)")
    s = pinhole(cam["to_world"], cam["width"], cam["height"], cam["fx"], cam["fy"],
                cam["cx"], cam["cy"], **(clip or {}))
    s["film"]["pixel_format"] = pixel_format
    return s


def clip_for(manifest: dict, cams: list[dict]) -> dict:
    """Clip planes scaled to the composition: its objects' bounds and the cameras' distance
    to them (a millimetre-scale composition is not clipped away by Mitsuba's 1 cm)."""
    b = np.array([o["bounds"] for o in manifest["objects"].values()], np.float64).reshape(-1, 2, 3)
    centre = b.mean((0, 1)) if len(b) else np.zeros(3)
    sizes = [float(np.linalg.norm(x[1] - x[0])) for x in b]
    dists = [float(np.linalg.norm(np.asarray(c["to_world"])[:3, 3] - centre)) for c in cams]
    return clip_planes(max(sizes + dists + [1e-30]))
