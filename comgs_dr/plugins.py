"""Registration of comgs_dr's Mitsuba plugins for whichever variant is active.

``install_variant_callback()`` hooks ``mi.detail.add_variant_callback`` so that a
later ``mi.set_variant(...)`` registers the plugins in the new variant too: a
Mitsuba pipeline only needs ``import comgs_dr`` before loading our XML.
"""
import mitsuba as mi

from comgs_dr.core.variant import is_supported_variant
from comgs_dr.emitters import octenvmap
from comgs_dr.integrators import comgs_composite, sop_pbr, surfel_gbuffer
from comgs_dr.surfels import shape

SHAPES = ("surfels",)
INTEGRATORS = ("surfel_gbuffer", "sop_pbr", "comgs_composite")
EMITTERS = ("octenvmap",)
_registered: set[str] = set()
_callback_installed = False


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
        for p in EMITTERS:
            mi.register_emitter(p, _refuse("emitter", p))
        _registered.add(name)
        return
    # Each module builds its variant-specific class when the plugin is first instantiated.
    shape.register()
    octenvmap.register()
    surfel_gbuffer.register()
    sop_pbr.register()
    comgs_composite.register()
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
