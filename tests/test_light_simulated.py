"""SimulatedLight: the paper's two illuminators lighting a scene, with ambient light."""

from __future__ import annotations

import numpy as np
import pytest

from tdfd import Camera
from tdfd.errors import InputError
from tdfd.illumination import PAPER_MASK
from tdfd.light import SimulatedLight

HW = (256, 320)


def _bright_width_px(irr: np.ndarray) -> float:
    """Total width (px) of the bright columns on the middle row (box-filtered edges count by coverage)."""
    return float(irr[HW[0] // 2].sum())


@pytest.fixture(scope="module")
def light():
    return SimulatedLight(Camera.preset("reference"))


@pytest.mark.parametrize("d", [0.3, 0.5, 1.0])
def test_coherent_keeps_its_physical_size(light, d):
    cam = light.camera
    irr = light.pattern_irradiance("coherent", np.full(HW, d))
    want = 2 * PAPER_MASK.width_m * cam.sensor_distance_m / (d * cam.pixel_pitch_m)  # two bars, 1/d in pixels
    assert _bright_width_px(irr) == pytest.approx(want, rel=0.02)
    assert irr.max() == pytest.approx(1.0)
    # sharp at every distance: every edge crosses from dark to bright within 2 px
    row = irr[HW[0] // 2]
    ramps = np.sum((row > 0.02) & (row < 0.98))
    assert ramps <= 4 * 2


def test_projector_sharp_at_focus_blurred_outside_and_inverse_square(light):
    def ramp_px(d):
        row = light.pattern_irradiance("projector", np.full(HW, d))[HW[0] // 2]
        peak = row.max()
        return np.sum((row > 0.02 * peak) & (row < 0.98 * peak)), peak

    sharp, peak_focus = ramp_px(0.568)
    blurred_far, peak_far = ramp_px(1.0)
    blurred_near, _ = ramp_px(0.3)
    assert sharp <= 8 and blurred_far > 3 * sharp and blurred_near > 3 * sharp
    assert peak_focus == pytest.approx(1.0, abs=0.01)
    assert peak_far < (0.568 / 1.0) ** 2 * 1.01  # falls at least as 1/d^2 (and blur lowers the peak)
    # the projector's source power is set so that its peak equals `power` at the near end
    assert light.source_power("projector") * (0.568 / 0.3) ** 2 == pytest.approx(light.power)


def test_radiance_is_albedo_times_ambient_plus_pattern():
    cam = Camera.preset("reference")
    light = SimulatedLight(cam, ambient=0.25, power=0.6)
    rng = np.random.default_rng(0)
    albedo, depth = rng.uniform(0.2, 0.9, HW), np.full(HW, 0.6)
    np.testing.assert_allclose(light.radiance(albedo, depth), 0.25 * albedo)  # off: ambient only
    light.on("coherent")
    irr = light.pattern_irradiance("coherent", depth)
    np.testing.assert_allclose(light.radiance(albedo, depth), albedo * (0.25 + 0.6 * irr), rtol=1e-6)
    assert light.pattern == "coherent"
    light.off()
    assert light.pattern is None
    np.testing.assert_allclose(light.radiance(albedo, depth), 0.25 * albedo)


def test_patterns_are_checked():
    light = SimulatedLight(Camera.preset("reference"), patterns=("coherent",))
    with pytest.raises(InputError, match="cannot show pattern 'projector'"):
        light.on("projector")
    assert not light.is_on
    light.on()  # the default: the first pattern
    assert light.pattern == "coherent"
    with pytest.raises(InputError):
        SimulatedLight(Camera.preset("reference"), patterns=("laser",))
    with pytest.raises(InputError):
        SimulatedLight(Camera.preset("reference"), power=0.0)
