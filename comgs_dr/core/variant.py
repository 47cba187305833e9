"""Mitsuba variant selection and the helpers that build per-variant plugin classes.

Plugin registration itself lives in :mod:`comgs_dr.plugins` (a variant callback installed
when the package is imported), so selecting a variant here registers our plugins too.
"""
from __future__ import annotations

import importlib
import importlib.metadata

import drjit as dr
import mitsuba as mi

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
    usable = [v for v in available if is_supported_variant(v)]
    if name not in available:
        raise ValueError(f"set_variant('{name}'): unknown variant; comgs_dr runs in "
                         f"{', '.join(['auto'] + usable)} (auto: cuda_ad_rgb where a CUDA "
                         f"device is usable, else llvm_ad_rgb)")
    if name.startswith("cuda_") and not dr.has_backend(dr.JitBackend.CUDA):
        raise ValueError(f"set_variant('{name}'): no CUDA device/driver is available here; "
                         f"use llvm_ad_rgb (the CPU) or auto")
    if not is_supported_variant(name):
        raise ValueError(f"set_variant('{name}'): comgs_dr runs in llvm_ad_rgb or cuda_ad_rgb "
                         "(RGB + AD JIT variants)")
    mi.set_variant(name)          # comgs_dr.plugins' variant callback registers the plugins
    return name


def package_version() -> str:
    """The installed comgs_dr version (recorded in generated datasets and weights)."""
    try:
        return importlib.metadata.version("comgs_dr")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def variant() -> str | None:
    """The active Mitsuba variant (None if none is set)."""
    return mi.variant()


def is_supported_variant(name: str | None) -> bool:
    """Our kernels run in the JIT + AD RGB variants: llvm_ad_rgb and cuda_ad_rgb."""
    return name in ("llvm_ad_rgb", "cuda_ad_rgb")




def variant_class(name: str, methods: type, base: type) -> type:
    """Subclass ``base`` (a per-variant nanobind type) with the methods of ``methods``.

    nanobind types accept a single base, so the plugin's methods live on a plain
    class and are copied into one subclass per variant; ``isinstance(x, methods)``
    is replaced by :func:`is_kind`.
    """
    ns = {}
    for cls in reversed(methods.__mro__[:-1]):          # mixins first, ``methods`` last
        ns.update({k: v for k, v in vars(cls).items() if k not in ("__dict__", "__weakref__")})
    ns["_comgs_kind"] = methods.__name__
    return type(name, (base,), ns)


def is_kind(obj, methods: type) -> bool:
    """True if ``obj`` was built by :func:`variant_class` from ``methods``."""
    return getattr(type(obj), "_comgs_kind", None) == methods.__name__


class AttachedRender:
    """``render`` / ``render_forward`` / ``render_backward`` of an AD integrator whose image
    is a differentiable expression ``self.render_attached(scene, sensor, seed, spp)``:
    forward and reverse mode differentiate that expression (as Mitsuba's AD integrators
    do with their primal pass). ``plugin_name`` names the plugin in errors."""
    plugin_name = "integrator"

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not develop:
            raise RuntimeError(f"{self.plugin_name}: only develop=True rendering is supported")
        with dr.suspend_grad():
            img = self.render_attached(scene, sensor, seed, spp)
            dr.eval(img)
        return img

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        with dr.resume_grad():
            img = self.render_attached(scene, sensor, seed, spp)
            dr.forward_to(img, flags=self._grad_flags())
            return dr.grad(img)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        with dr.resume_grad():
            img = self.render_attached(scene, sensor, seed, spp)
            dr.backward_from(img * grad_in, flags=self._grad_flags())

    def _grad_flags(self):
        """A view in which ``render_attached`` saw nothing it differentiates (it sets
        ``sees_nothing``: an object out of frame, a camera looking away) has a zero gradient,
        as with Mitsuba's own integrators, instead of Dr.Jit's "does not depend on the input
        variable(s)" stopping a multi-view loop. Elsewhere that error stays: it is what a
        user optimising a parameter the integrator does not differentiate should see."""
        if getattr(self, "sees_nothing", False):
            return dr.ADFlag.Default | dr.ADFlag.AllowNoGrad
        return dr.ADFlag.Default


def mitsuba_ad_base(name: str = "RBIntegrator"):
    """Mitsuba's Python AD integrator base class (``RBIntegrator``, ``ADIntegrator``)
    built for the active variant."""
    from mitsuba.python.ad.integrators import (
        common as mi_common,  # needs an active variant
    )
    if not issubclass(mi_common.ADIntegrator, mi.CppADIntegrator):
        mi_common = importlib.reload(mi_common)   # Mitsuba's own callback has not run yet
    return getattr(mi_common, name)
