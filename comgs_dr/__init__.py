"""comgs_dr: object-scene composition with 2D Gaussian surfels and Surface Octahedral
Probes (ComGS) on Dr.Jit / Mitsuba 3.

Import this package before (or after) choosing a Mitsuba variant: our plugins
(``surfels`` shape, ``surfel_gbuffer`` integrator) are registered for every JIT
variant that becomes active.
"""
from ._env import ensure_llvm_path

ensure_llvm_path()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from . import plugins as _plugins  # noqa: E402

__version__ = "0.1.0"
__all__ = ["set_variant", "variant", "__version__"]

_JIT_VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb")


def set_variant(name: str = "auto") -> str:
    """Select the Mitsuba variant and register our plugins in it.

    ``"auto"`` picks ``cuda_ad_rgb`` when a CUDA device is usable, else
    ``llvm_ad_rgb``. Explicit JIT variant names are passed through. Scalar
    variants are refused: every kernel here is a Dr.Jit JIT kernel.

    Returns the name of the active variant.
    """
    if not isinstance(name, str):
        raise TypeError(f"set_variant(name): expected a string, got {type(name).__name__}")
    available = mi.variants()
    if name == "auto":
        name = "llvm_ad_rgb"
        if "cuda_ad_rgb" in available and dr.has_backend(dr.JitBackend.CUDA):
            name = "cuda_ad_rgb"
    if name.startswith("scalar_"):
        raise ValueError(
            f"set_variant('{name}'): comgs_dr needs a JIT variant (llvm_ad_rgb or "
            "cuda_ad_rgb); scalar variants cannot run its Dr.Jit kernels")
    if name not in available:
        raise ValueError(f"set_variant('{name}'): unknown variant; this Mitsuba build "
                         f"has {', '.join(available)}")
    if name.startswith("cuda_") and not dr.has_backend(dr.JitBackend.CUDA):
        raise RuntimeError(f"set_variant('{name}'): no CUDA device/driver is available")
    if not _plugins.is_supported_variant(name):
        raise ValueError(f"set_variant('{name}'): comgs_dr runs in llvm_ad_rgb or cuda_ad_rgb "
                         "(RGB + AD JIT variants)")
    mi.set_variant(name)
    _plugins.register_all()  # also done by the variant callback; idempotent
    return name


def variant() -> str | None:
    """The active Mitsuba variant (None if none is set)."""
    return mi.variant()


_plugins.install_variant_callback()
