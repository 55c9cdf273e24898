"""ROI selection and aggregation on the tile grid; the in-focus power formula; sharpness."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tdfd import Camera
from tdfd.autofocus.aggregate import aggregate_depth
from tdfd.autofocus.focus_power import in_focus_power_dpt
from tdfd.autofocus.roi import Roi, roi_crop_box, roi_tile_mask
from tdfd.autofocus.sharpness import sharpness
from tdfd.errors import InputError
from tdfd.grid import grid_shape, tile_centres

CAM = Camera.preset("reference")


def test_roi_parse_centre_clip():
    assert Roi.parse("10,20,30,40") == Roi(10, 20, 30, 40)
    assert str(Roi(1, 2, 3, 4)) == "1,2,3,4"
    assert Roi.centre((256, 320)) == Roi(80, 64, 160, 128)
    assert Roi(300, 200, 100, 100).clip((256, 320)) == Roi(300, 200, 20, 56)
    for bad in ("1,2,3", "a,b,c,d"):
        with pytest.raises(InputError):
            Roi.parse(bad)
    with pytest.raises(InputError):
        Roi(0, 0, 0, 5)
    with pytest.raises(InputError):
        Roi(400, 0, 5, 5).clip((256, 320))


@pytest.mark.parametrize("roi", [Roi(80, 64, 160, 128), Roi(0, 0, 64, 64), Roi(100, 90, 10, 10), Roi(200, 150, 120, 106)])
def test_mask_matches_tile_centres_and_crop(roi):
    hw, tile, stride = (256, 320), 64, 32
    gh, gw = grid_shape(*hw, tile, stride)
    mask = roi_tile_mask(roi, (gh, gw), tile, stride)
    cy, cx = tile_centres(*hw, tile, stride)
    inside = ((cy.numpy()[:, None] >= roi.y - 0.5) & (cy.numpy()[:, None] < roi.y + roi.h - 0.5)
              & (cx.numpy()[None, :] >= roi.x - 0.5) & (cx.numpy()[None, :] < roi.x + roi.w - 0.5))
    if inside.any():
        np.testing.assert_array_equal(mask, inside)
    else:
        assert mask.sum() == 1  # the nearest tile
    # the grid-aligned crop holds exactly the masked tiles
    y0, y1, x0, x1 = roi_crop_box(roi, hw, tile, stride)
    assert y0 % stride == 0 and x0 % stride == 0
    ch, cw = grid_shape(y1 - y0, x1 - x0, tile, stride)
    assert ch * cw == mask.sum()
    sub = roi_tile_mask(roi, (ch, cw), tile, stride, offset=(y0, x0))
    assert sub.all()


def test_aggregate_robust_to_outliers():
    rng = np.random.default_rng(0)
    q = 1 / 0.5 + rng.normal(0, 0.02, (5, 7))
    depth = 1 / q
    depth[0, :3] = 5.0  # far outliers (e.g. background tiles)
    depth[4, 6] = 0.05  # a wild near outlier
    conf = np.full(depth.shape, 0.9)
    a = aggregate_depth(depth, conf)
    assert a.depth_m == pytest.approx(0.5, rel=0.01)
    assert a.inliers == depth.size - 4 and a.tiles == depth.size
    assert a.spread_dpt < 0.05
    naive = 1 / np.mean(1 / depth)
    assert abs(naive - 0.5) > 0.05  # the plain mean is not robust


def test_aggregate_confidence_weighting():
    depth = np.full((4, 4), 0.4)
    depth[:, :2] = 0.8  # half the ROI disagrees, with near-zero confidence
    conf = np.full((4, 4), 0.9)
    conf[:, :2] = 0.01
    a = aggregate_depth(depth, conf)
    assert a.depth_m == pytest.approx(0.4, rel=1e-3)
    assert a.confidence == pytest.approx((0.9 + 0.01) / 2)
    conf[:, :2], conf[:, 2:] = 0.9, 0.01
    assert aggregate_depth(depth, conf).depth_m == pytest.approx(0.8, rel=1e-3)


def test_aggregate_mask_nonfinite_and_zero_confidence():
    depth = np.full((3, 3), 0.6)
    depth[0, 0] = np.nan
    conf = np.zeros((3, 3))
    a = aggregate_depth(depth, conf)
    assert a.depth_m == pytest.approx(0.6) and a.confidence == 0.0
    mask = np.zeros((3, 3), bool)
    mask[2, 2] = True
    depth[2, 2] = 0.3
    assert aggregate_depth(depth, np.ones((3, 3)), mask).depth_m == pytest.approx(0.3)
    with pytest.raises(InputError):
        aggregate_depth(np.full((2, 2), np.nan), np.ones((2, 2)))
    with pytest.raises(InputError):
        aggregate_depth(np.ones((2, 2)), np.ones((3, 2)))


@pytest.mark.parametrize("depth", [0.3, 0.45, 0.7, 1.0, 3.0])
def test_in_focus_power_round_trip(depth):
    from tdfd.optics.thin_lens import camera_blur_radii_px

    p = in_focus_power_dpt(CAM, depth)
    assert p == pytest.approx(1 / depth + 1 / CAM.sensor_distance_m - 1 / CAM.fixed_focal_length_m)
    assert abs(float(camera_blur_radii_px(CAM, depth, p))) < 1e-6
    assert CAM.focus_distance_m(p) == pytest.approx(depth)
    # 1 px of blur radius is about 0.21 dpt for this camera
    dp = CAM.pixel_pitch_m / CAM.blur_scale_m_dpt
    assert abs(float(camera_blur_radii_px(CAM, depth, p + dp))) == pytest.approx(1.0, rel=1e-4)


def test_in_focus_power_infinity():
    assert in_focus_power_dpt(CAM, math.inf) == pytest.approx(0.0, abs=1e-9)


def test_sharpness_orders_blur_and_ignores_gain():
    import cv2

    rng = np.random.default_rng(1)
    img = rng.uniform(0.2, 0.8, (64, 80)).astype(np.float32)
    for measure in ("laplacian", "tenengrad"):
        values = [sharpness(cv2.GaussianBlur(img, (0, 0), s) if s else img, measure=measure) for s in (0, 1, 2, 4)]
        assert values == sorted(values, reverse=True)
        assert sharpness(0.5 * img, measure=measure) == pytest.approx(sharpness(img, measure=measure), rel=1e-4)
    assert sharpness(img, Roi(10, 10, 20, 20)) > 0
    with pytest.raises(InputError):
        sharpness(img, measure="fft")
