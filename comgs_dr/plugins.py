"""Registration of comgs_dr's Mitsuba plugins for whichever variant is active.

``install_variant_callback()`` hooks ``mi.detail.add_variant_callback`` so that a
later ``mi.set_variant(...)`` registers the plugins in the new variant too: a
Mitsuba pipeline only needs ``import comgs_dr`` before loading our XML.
"""
import mitsuba as mi

SHAPES = ("surfels",)
INTEGRATORS = ("surfel_gbuffer", "sop_pbr")
_registered: set[str] = set()
_callback_installed = False


def is_supported_variant(name: str | None) -> bool:
    """Our kernels run in the JIT + AD RGB variants: llvm_ad_rgb and cuda_ad_rgb."""
    return name in ("llvm_ad_rgb", "cuda_ad_rgb")


def _refuse(kind: str, plugin: str):
    def factory(props):
        raise RuntimeError(
            f"comgs_dr {kind} '{plugin}' needs the llvm_ad_rgb or cuda_ad_rgb variant; "
            f"the active variant is '{mi.variant()}'. Call comgs_dr.set_variant('auto').")
    return factory


def register_all() -> None:
    """Register every plugin in the active variant (idempotent)."""
    name = mi.variant()
    if name is None or name in _registered:
        return
    if not is_supported_variant(name):
        for p in SHAPES:
            mi.register_shape(p, _refuse("shape", p))
        for p in INTEGRATORS:
            mi.register_integrator(p, _refuse("integrator", p))
        _registered.add(name)
        return
    # Imported lazily: the modules build variant-specific types when used.
    from .surfels.shape import register as register_shape
    from .integrators.gbuffer import register as register_gbuffer
    from .integrators.pbr import register as register_pbr
    register_shape()
    register_gbuffer()
    register_pbr()
    _registered.add(name)


def _on_variant_change(old, new) -> None:
    register_all()


def install_variant_callback() -> None:
    global _callback_installed
    if _callback_installed:
        return
    mi.detail.add_variant_callback(_on_variant_change)
    _callback_installed = True
    register_all()  # a variant may already be active
