"""What the simulated bench charges for computation: median wall times measured on this machine.

The bench's clock is simulated, but the controller's computation is real: the estimator,
each relative-blur measurement and each cross-blur search of its evidence. Each is timed
here once, on seeded frames of the bench's read-out size and ROI (median of repeated runs),
and the bench adds the time to every trial that used it (:class:`~tdfd.autofocus.sim.bench.SimBench`).
"""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np

from ...camera import Camera
from ...errors import TdfdError
from ..cross_blur import cross_blur_focus
from ..region_cross_blur import fit_region_cross_blur
from ..relative_blur import relative_blur_px2, relative_blur_search_px2
from ..roi import Roi, roi_crop_box

__all__ = ["median_wall_s", "calibration_texture", "evidence_wall_s", "region_fit_wall_s", "cross_blur_wall_s", "pair_cross_blur_wall_s",
           "estimator_wall_s"]


def median_wall_s(run: Callable[[], object], repeats: int, warm_up: bool = True) -> float:
    """Median wall time (s) of ``run()`` over ``repeats`` calls, after an untimed warm-up call."""
    if warm_up:
        run()
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def calibration_texture(readout_hw: tuple[int, int]) -> np.ndarray:
    """A smooth random texture of the read-out size (seeded) that the evidence timings run on."""
    import cv2

    rng = np.random.default_rng(54321)
    return cv2.GaussianBlur(rng.uniform(0.2, 0.8, readout_hw).astype(np.float32), (0, 0), 1.0)


def region_fit_wall_s(camera: Camera, roi: Roi, readout_hw: tuple[int, int], repeats: int = 5,
                      disk: bool = False) -> float:
    """One region fit over the ROI's central square (the assisted controller's step 3):
    :func:`tdfd.dfd.region_fit.fit_region` (its estimator built before the timing, as the
    controller reuses it), or with ``disk`` the disk cross-blur
    (:func:`tdfd.autofocus.region_cross_blur.fit_region_cross_blur`) of a lens told it is a disk."""
    import cv2

    a = calibration_texture(readout_hw)
    b = cv2.GaussianBlur(a, (0, 0), 2.0)
    ra, rb = roi.crop(a), roi.crop(b)
    if disk:
        def fit() -> None:
            try:
                fit_region_cross_blur(ra, rb, camera.lens_powers_dpt, camera, psf_family="pillbox")
            except TdfdError:  # the timing texture need not hold a minimum in range: the search ran all the same
                pass

        return median_wall_s(fit, repeats)
    from ...dfd.region_fit import fit_region  # torch: loaded only for a bench with a light (the CLI imports this torch-free)

    return median_wall_s(lambda: fit_region(ra, rb, camera), repeats)


def evidence_wall_s(camera: Camera, roi: Roi, readout_hw: tuple[int, int], repeats: int = 5) -> float:
    """One relative-blur measurement on the ROI (the controller's evidence,
    :func:`tdfd.autofocus.relative_blur.relative_blur_px2` with its uncertainty, searched over the
    camera's range: :func:`~tdfd.autofocus.relative_blur.relative_blur_search_px2`)."""
    import cv2

    a = calibration_texture(readout_hw)
    b = cv2.GaussianBlur(a, (0, 0), 2.0)
    search = relative_blur_search_px2(camera)
    return median_wall_s(lambda: relative_blur_px2(a, b, roi, max_px2=search), repeats)


def _frames(readout_hw: tuple[int, int]) -> list[tuple[np.ndarray, float]]:
    import cv2

    a = calibration_texture(readout_hw)
    return [(cv2.GaussianBlur(a, (0, 0), s), p) for s, p in ((1.5, 1.7), (2.5, 2.7), (1.0, 2.0))]


def cross_blur_wall_s(camera: Camera, roi: Roi, readout_hw: tuple[int, int], repeats: int = 3) -> float:
    """One cross-blur focus search on three frames of the ROI, both PSF families (the
    dearest the controller runs: it is charged for every search on three or more frames)."""
    frames = _frames(readout_hw)
    return median_wall_s(lambda: cross_blur_focus(frames, camera, roi), repeats, warm_up=False)


def pair_cross_blur_wall_s(camera: Camera, roi: Roi, readout_hw: tuple[int, int], repeats: int = 5) -> float:
    """One cross-blur focus search on the two frames of a DFD pair, the disk family only (the
    2-frame check of a known disk PSF, :class:`~tdfd.autofocus.dfd.DFDController` ``psf_family``)."""
    frames = _frames(readout_hw)[:2]
    return median_wall_s(lambda: cross_blur_focus(frames, camera, roi, shapes=("pillbox",)), repeats)


def estimator_wall_s(estimator: Any, roi: Roi, readout_hw: tuple[int, int], repeats: int = 7) -> float:
    """The estimator on a pair of frames of the size the DFD controller sends (the grid-aligned
    crop around the ROI); 0 without an estimator."""
    if estimator is None:
        return 0.0
    y0, y1, x0, x1 = roi_crop_box(roi, readout_hw, estimator.tile, estimator.stride)
    rng = np.random.default_rng(12345)
    a = rng.uniform(0.2, 0.8, (y1 - y0, x1 - x0)).astype(np.float32)
    b = rng.uniform(0.2, 0.8, (y1 - y0, x1 - x0)).astype(np.float32)
    return median_wall_s(lambda: estimator(a, b), repeats)
