import atexit
import os
import shutil
import tempfile

import numpy as np
import pytest

import comgs_dr

# The notebooks (collected from notebooks/ by nbmake in the same run) execute at smoke-test
# sizes into a temporary folder: their kernels inherit this environment.
os.environ.setdefault("COMGS_NOTEBOOK_TINY", "1")
if "COMGS_NOTEBOOK_OUT" not in os.environ:     # ours: removed when the test process exits
    os.environ["COMGS_NOTEBOOK_OUT"] = tempfile.mkdtemp(prefix="comgs_notebooks_")
    atexit.register(shutil.rmtree, os.environ["COMGS_NOTEBOOK_OUT"], ignore_errors=True)
os.environ.setdefault("MPLBACKEND", "Agg")

if os.environ.get("COMGS_GUARD_ALLOC") == "1":       # diagnostic: see tests/guard_alloc.py
    from guard_alloc import allocator
    allocator().__enter__()


def pytest_addoption(parser):
    parser.addoption("--mitsuba-variant", default=os.environ.get("COMGS_TEST_VARIANT",
                                                                 "llvm_ad_rgb"),
                     help="the Mitsuba variant the tests run in (llvm_ad_rgb, the first-class "
                          "CPU target, by default; cuda_ad_rgb: benchmarks/gpu_check.py)")


@pytest.fixture(scope="session", autouse=True)
def variant(request):
    """Every test runs in ``--mitsuba-variant`` (llvm_ad_rgb unless told)."""
    return comgs_dr.set_variant(request.config.getoption("--mitsuba-variant"))


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny torch models: one intra-op thread (spinning workers made them ~4x slower on a busy
    2-core machine); restored after the module."""
    import torch
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def random_surfels(rng, n=60, extent=0.5, scale=(0.05, 0.2), sh_degree=1, opacity=(0.5, 3.0)):
    """Random surfels in a cube, as a SurfelParams (test helper)."""
    from comgs_dr.surfels import SurfelParams
    k = (sh_degree + 1) ** 2
    return SurfelParams.from_numpy(
        means=rng.uniform(-extent, extent, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        log_scales=np.log(rng.uniform(scale[0], scale[1], (n, 2))),
        opacity_logit=rng.uniform(opacity[0], opacity[1], n),
        sh=rng.normal(0, 0.4, (n, k, 3)),
        albedo=rng.uniform(0, 1, (n, 3)), roughness=rng.uniform(0, 1, n),
        metallic=rng.uniform(0, 1, n))


def error_chain_text(exc: BaseException) -> str:
    """Messages of an exception and its causes (Mitsuba wraps plugin errors)."""
    parts, seen = [], set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        parts.append(str(exc))
        exc = exc.__cause__ or exc.__context__
    return "\n".join(parts)


def make_tiny_object_dataset(root):
    """A two-coloured capsule under a sky with a bright spot: 16 train + 4 test views, 32 px
    (NeRF-synthetic folder ``root/ds``, returned)."""
    import mitsuba as mi
    import trimesh

    from comgs_dr.data import synthetic as syn
    trimesh.creation.capsule(height=0.8, radius=0.45).export(root / "obj.ply")
    sky = np.full((16, 32, 3), 0.6, np.float32)
    sky[2:5, 4:8] = 20.0
    mi.Bitmap(sky).write(str(root / "sky.exr"))
    cfg = syn.ObjectDatasetConfig(mesh=root / "obj.ply", envmap=root / "sky.exr", out_dir=root / "ds",
                                  n_train=16, n_test=4, resolution=32, spp=16, spp_aov=2, max_depth=3,
                                  relight_envmaps=(), texture=None, up_axis="z", base_color=(0.7, 0.3, 0.2))
    syn.make_object_dataset(cfg, progress=False)
    return root / "ds"


def make_tiny_step1_run(root, n_surfels: int = 3000):
    """A 32 px dataset of the demo object + mesh-sampled surfels written as a finished
    step-1 run; returns (run folder, sky map path)."""
    import json

    import trimesh

    from comgs_dr.data.procedural import procedural_object, procedural_sky
    from comgs_dr.data.synthetic import ObjectDatasetConfig, make_object_dataset
    from comgs_dr.surfels import from_mesh, save_ply
    from comgs_dr.train.run import write_run_info
    mesh = procedural_object(root / "object.ply")
    sky = procedural_sky(root / "sky.exr", width=64)
    ds = root / "data"
    make_object_dataset(ObjectDatasetConfig(
        mesh=mesh, envmap=sky, out_dir=ds, n_train=10, n_test=2, resolution=32, spp=4,
        spp_aov=2, relight_envmaps=(), up_axis="z", texture=None,
        base_color=(0.7, 0.45, 0.3)), progress=False)
    meta = json.loads((ds / "meta.json").read_text())
    tm = trimesh.load(mesh, force="mesh")
    tm.apply_transform(np.asarray(meta["object"]["object_to_world"]))
    run = root / "run"
    write_run_info(run, ds, "object", 1, False)
    save_ply(from_mesh(tm, n_surfels, seed=0), str(run / "point_cloud.ply"))
    return run, sky
