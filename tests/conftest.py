import os
import tempfile

import numpy as np
import pytest

import comgs_dr

# The notebooks (collected from notebooks/ by nbmake in the same run) execute at smoke-test
# sizes into a temporary folder: their kernels inherit this environment.
os.environ.setdefault("COMGS_NOTEBOOK_TINY", "1")
os.environ.setdefault("COMGS_NOTEBOOK_OUT", tempfile.mkdtemp(prefix="comgs_notebooks_"))
os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session", autouse=True)
def variant():
    """Every test runs in llvm_ad_rgb (the first-class CPU target)."""
    return comgs_dr.set_variant("llvm_ad_rgb")


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
