"""The dataset gbuffer's AOV render writes inside its film (synthetic_io.GBUFFER_AOVS)."""
import drjit as dr
import mitsuba as mi
import pytest

from comgs_dr.data import synthetic_io as sio


def _render(variant, aovs: str, res: int = 16):
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene", "e": {"type": "constant"},
        "s": {"type": "sphere", "bsdf": {"type": "diffuse"}},
        "sensor": {"type": "perspective", "fov": 50.0,
                   "to_world": T().look_at([0, -3, 1], [0, 0, 0], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "pixel_format": "rgba", "rfilter": {"type": "box"}}}})
    aov = mi.load_dict({"type": "aov", "aovs": aovs, "inner": {
        "type": "direct", "hide_emitters": True, "emitter_samples": 0, "bsdf_samples": 1}})
    debug = dr.flag(dr.JitFlag.Debug)
    dr.set_flag(dr.JitFlag.Debug, True)                 # bounds-checked scatters
    try:
        mi.render(scene, integrator=aov, spp=2)
        dr.sync_thread()
    finally:
        dr.set_flag(dr.JitFlag.Debug, debug)
    return scene.sensors()[0].film().bitmap().channel_count()


def test_gbuffer_aovs_write_in_bounds(variant, capfd):
    """With the three AOVs alone the block has 16 channels, and Mitsuba writes out of
    bounds (the reason for the extra AOV); with GBUFFER_AOVS it does not."""
    bad = "albedo:albedo,nn:sh_normal,dd:depth"
    if _render(variant, bad) == 15:
        err = capfd.readouterr().err
        if "out-of-bounds" not in err:
            pytest.skip("this Mitsuba build writes a 16-channel block in bounds")
    capfd.readouterr()
    assert _render(variant, sio.GBUFFER_AOVS) != 15
    assert "out-of-bounds" not in capfd.readouterr().err
