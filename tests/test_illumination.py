"""Active illumination: the coherent pattern stays sharp at every distance, the projector's
blurs away from its 56.8 cm focus as its depth of field predicts."""

import math

import pytest
import torch

from tdfd import Camera
from tdfd.errors import InputError
from tdfd.illumination import (PAPER_MASK, CoherentIllumination, MaskPattern, ProjectorIllumination, box_square_wave,
                               illuminate, speckle, speckle_grain_px, target_coordinates)

CAM = Camera.preset("reference")


def _row_profile(img: torch.Tensor) -> torch.Tensor:
    """Centre row of a (1, 1, H, W) image, float64."""
    return img[0, 0, img.shape[-2] // 2].double()


def _crossings(p: torch.Tensor, level: float) -> list[float]:
    """Sub-pixel positions where the profile crosses ``level``."""
    out = []
    for j in range(len(p) - 1):
        a, b = float(p[j]), float(p[j + 1])
        if (a - level) * (b - level) < 0:
            out.append(j + (level - a) / (b - a))
    return out


def _edge_width(p: torch.Tensor, peak: float) -> float:
    """10-90 % width (px) of the first rising edge of a profile with plateau ``peak``."""
    lo = _crossings(p, 0.1 * peak)
    hi = _crossings(p, 0.9 * peak)
    return hi[0] - lo[0]


def _partial_pixels(p: torch.Tensor, peak: float = 1.0) -> int:
    return int(((p > 0.01 * peak) & (p < 0.99 * peak)).sum())


def _bars(p: torch.Tensor, split: list[int]) -> list[tuple[float, float]]:
    """(area, centroid) of the profile between consecutive split points: a box-filtered
    shape keeps its exact area and centroid."""
    out = []
    x = torch.arange(len(p), dtype=torch.float64)
    for a, b in zip(split, split[1:]):
        seg, xs = p[a:b], x[a:b]
        out.append((float(seg.sum()), float((seg * xs).sum() / seg.sum())))
    return out


def test_coherent_pattern_is_identical_in_physical_units_at_every_distance():
    las = CoherentIllumination()  # the paper's two 6.2 mm x 18.9 mm bars, 6.2 mm apart
    for d in (0.3, 0.45, 0.568, 0.75, 1.0):
        depth = torch.full((1, 1, 16, 400), d, dtype=torch.float64)
        p = _row_profile(las.render(CAM, depth))
        assert float(p.max()) == pytest.approx(1.0)  # a collimated beam: same irradiance
        footprint = CAM.pixel_pitch_m * d / CAM.sensor_distance_m
        centre = (400 - 1) / 2
        (w1, c1), (w2, c2) = _bars(p, [0, 200, 400])
        # each bar is 6.2 mm wide and centred 6.2 mm from the axis, at every distance
        assert w1 * footprint == pytest.approx(6.2e-3, rel=1e-5)
        assert w2 * footprint == pytest.approx(6.2e-3, rel=1e-5)
        # (a sampled box-filtered edge biases a centroid by < 0.02 px)
        assert (c1 - centre) * footprint == pytest.approx(-6.2e-3, abs=0.02 * footprint)
        assert (c2 - centre) * footprint == pytest.approx(6.2e-3, abs=0.02 * footprint)
        # sharp: each of the 4 edges is at most one partially covered pixel
        assert _partial_pixels(p) <= 4


def test_coherent_pattern_shrinks_in_pixels_as_one_over_distance():
    las = CoherentIllumination()
    widths = {}
    for d in (0.3, 0.6):
        p = _row_profile(las.render(CAM, torch.full((1, 1, 8, 400), d, dtype=torch.float64)))
        widths[d] = _bars(p, [0, 200])[0][0]
    assert widths[0.3] / widths[0.6] == pytest.approx(2.0, rel=1e-5)
    assert widths[0.3] == pytest.approx(6.2e-3 * CAM.sensor_distance_m / (0.3 * CAM.pixel_pitch_m), rel=1e-5)


def test_projector_blur_follows_its_depth_of_field():
    proj = ProjectorIllumination()
    # the blur diameter reaches the circle of confusion exactly at the paper's DOF limits
    assert abs(float(proj.blur_angle_rad(0.568 - 0.125))) == pytest.approx(proj.coc_rad, rel=1e-6)
    assert abs(float(proj.blur_angle_rad(0.568 + 0.165))) == pytest.approx(proj.coc_rad, rel=1e-6)
    assert float(proj.blur_angle_rad(0.568)) == 0.0
    widths, bar_px = {}, {}
    for d in (0.30, 0.40, 0.443, 0.50, 0.568, 0.65, 0.733, 0.85, 1.0):
        img = proj.render(CAM, torch.full((1, 1, 8, 256), d, dtype=torch.float64))
        p = _row_profile(img)
        peak = (0.568 / d) ** 2  # the projection cone spreads the light
        assert float(p.max()) == pytest.approx(peak, rel=0.02)
        widths[d] = _edge_width(p, peak)
        x = _crossings(p, 0.5 * peak)
        bar_px[d] = x[1] - x[0]
        diameter_px = abs(float(proj.blur_angle_rad(d))) * CAM.sensor_distance_m / CAM.pixel_pitch_m
        # a straight edge blurred by a disk of diameter D rises 10-90 % over 0.687 D (plus the
        # pixel: a sharp sampled edge measures up to 1.6 px)
        assert widths[d] == pytest.approx(0.687 * diameter_px, abs=1.7 + 0.05 * diameter_px)
        if d == 0.568:  # sharp at best focus
            assert _partial_pixels(p, peak) <= 4
    near = [widths[d] for d in (0.30, 0.40, 0.443, 0.50, 0.568)]
    far = [widths[d] for d in (0.568, 0.65, 0.733, 0.85, 1.0)]
    assert near == sorted(near, reverse=True) and far == sorted(far)  # grows away from focus
    assert widths[0.30] > 8.0 and widths[1.0] > 4.0
    # the projected pattern keeps its size in pixels (cone and magnification cancel)
    assert max(bar_px.values()) - min(bar_px.values()) < 0.5
    assert bar_px[0.568] == pytest.approx(6.2e-3 * CAM.sensor_distance_m / (0.568 * CAM.pixel_pitch_m), abs=0.3)


def test_coherent_stays_sharp_where_the_projector_blurs():
    las, proj = CoherentIllumination(), ProjectorIllumination()
    for d in (0.31, 1.0):  # the paper's Fig. 8 (a) and (c)
        depth = torch.full((1, 1, 8, 400), d)
        pl = _row_profile(las.render(CAM, depth))
        pp = _row_profile(proj.render(CAM, depth))
        assert _partial_pixels(pl) <= 4
        assert _edge_width(pp, float(pp.max())) > 2.0


def test_diffraction_orders_sit_at_fixed_pixel_offsets():
    theta = 0.02
    las = CoherentIllumination(mask=MaskPattern("rect", width_m=2e-3, height_m=2e-3), orders=(1, 3),
                               order_angle_rad=(theta, theta))
    expected = CAM.sensor_distance_m * math.tan(math.asin(math.sin(theta))) / CAM.pixel_pitch_m
    for d in (0.4, 0.8):
        p = _row_profile(las.render(CAM, torch.full((1, 1, 9, 301), d, dtype=torch.float64)))
        blobs = _bars(p, [0, 103, 198, 301])
        assert [round(a, 6) for a, _ in blobs] == pytest.approx([2e-3 * CAM.sensor_distance_m / (d * CAM.pixel_pitch_m)] * 3)
        assert [c - 150 for _, c in blobs] == pytest.approx([-expected, 0.0, expected], abs=0.02)


def test_pattern_follows_a_depth_map():
    # a step in depth: each side shows the pattern at its own scale
    las = CoherentIllumination(mask=MaskPattern("grating", period_m=2e-3, beam_m=1.0))
    depth = torch.full((1, 1, 8, 200), 0.3)
    depth[..., 100:] = 0.6
    p = _row_profile(las.render(CAM, depth))
    x = _crossings(p, 0.5)
    left = [b - a for a, b in zip(x, x[1:]) if b < 95]
    right = [b - a for a, b in zip(x, x[1:]) if a > 105]
    assert sum(left) / len(left) == pytest.approx(2 * sum(right) / len(right), rel=0.05)


def test_masks_speckle_and_helpers():
    g = torch.Generator().manual_seed(0)
    s = speckle((128, 128), g, grain_px=3.0, batch=2)
    assert float(s.mean()) == pytest.approx(1.0, abs=1e-4)
    assert float(s.std()) == pytest.approx(1.0, abs=0.15)  # fully developed: contrast 1
    assert float(s.min()) >= 0.0
    assert speckle_grain_px(CAM) == pytest.approx(2.44 * 632.8e-9 * 12.5 / 5.3e-6)
    las = CoherentIllumination(speckle_contrast=0.5)
    depth = torch.full((1, 1, 32, 32), 0.5)
    a = las.render(CAM, depth, generator=torch.Generator().manual_seed(1))
    b = las.render(CAM, depth, generator=torch.Generator().manual_seed(1))
    assert torch.equal(a, b)
    with pytest.raises(InputError):
        las.render(CAM, depth)  # speckle needs a generator
    for kind in ("grating", "dots", "checker", "random", "rect", "bars"):
        m = MaskPattern(kind, period_m=1e-3, radius_m=0.3e-3, beam_m=20e-3)
        y, x, fp = target_coordinates(CAM, torch.full((1, 1, 64, 64), 0.5))
        c = m.coverage(y, x, fp)
        assert float(c.min()) >= 0.0 and float(c.max()) <= 1.0 and float(c.max()) > 0.5
    u = torch.linspace(0, 100, 10001)
    assert float(box_square_wave(u, 0.7, 0.4, 1.0).mean()) == pytest.approx(0.4, abs=0.01)
    alb = torch.full((1, 1, 4, 4), 0.5)
    assert torch.allclose(illuminate(alb, torch.ones_like(alb), ambient=0.2, power=2.0), torch.full_like(alb, 1.1))
    assert PAPER_MASK.half_extent_m == pytest.approx((9.45e-3, 9.3e-3))
    with pytest.raises(InputError):
        MaskPattern("hexagons")
    with pytest.raises(InputError):
        ProjectorIllumination(dof_near_m=1.0)
