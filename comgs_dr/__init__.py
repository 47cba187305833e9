"""comgs_dr: object-scene composition with 2D Gaussian surfels and Surface Octahedral
Probes (ComGS) on Dr.Jit / Mitsuba 3.

Import this package before (or after) choosing a Mitsuba variant: our plugins
(``surfels`` shape, ``surfel_gbuffer`` integrator) are registered for every JIT
variant that becomes active.
"""
from comgs_dr.core.env import ensure_llvm_path

ensure_llvm_path()

from comgs_dr import plugins as _plugins  # noqa: E402
from comgs_dr.core.variant import package_version, set_variant, variant  # noqa: E402

__version__ = package_version()
__all__ = ["set_variant", "variant", "__version__"]

_plugins.install_variant_callback()
