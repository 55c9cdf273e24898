"""Depth estimators for the autofocus loop: the shipped ONNX model, or the analytic stand-in.

Each is an :class:`~tdfd.autofocus.interfaces.Estimator`: ``(image_f1, image_f2)``, two
``(H, W)`` float32 frames of linear intensity in [0, 1] captured at the camera's two ECVFL
powers, to ``(depth_m, confidence)`` on the tile grid, with ``camera``, ``tile`` and
``stride`` attributes.

* :class:`OnnxEstimator`: an ONNX file of CONTRACT.md section 2 (camera and grid from its
  metadata) through :class:`tdfd.runtime.DepthRuntime`. No torch.
* :class:`AnalyticEstimator`: the torch Fourier-ratio estimator
  (:class:`tdfd.dfd.FourierRatioDFD`), the stand-in before a trained model exists.

:func:`load_estimator` picks one from a CLI-style spec.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import Camera
from ..contract import DEFAULT_MODEL_RELPATH, MODEL_KEY
from ..errors import InputError, ModelError
from ..runtime import DepthRuntime
from ..runtime import default_model_path as runtime_default_model_path
from .threads import torch_threads

__all__ = ["OnnxEstimator", "AnalyticEstimator", "load_estimator", "default_model_path", "suggested_min_confidence",
           "suggested_confidence_scale", "estimator_breathing", "ONNX_INTRA_THREADS"]

log = logging.getLogger(__name__)

#: onnxruntime intra-op threads (one is as fast as two for ROI-sized frames, and robust on a busy machine).
ONNX_INTRA_THREADS = 1


def default_model_path() -> Path:
    """The default model: :func:`tdfd.runtime.default_model_path` (``$TDFD_MODEL``, the
    packaged model, ``./models/reference.onnx``), or the checkout's shipped path (which then
    does not exist: the CLI says so and uses the analytic estimator)."""
    try:
        return Path(runtime_default_model_path())
    except ModelError:
        return Path(__file__).resolve().parents[2] / DEFAULT_MODEL_RELPATH


def _as_frame(image: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        return a[None, None]
    if a.ndim == 4 and a.shape[:2] == (1, 1):
        return a
    raise InputError(f"{name} must be (H, W) or (1, 1, H, W), got {a.shape}")


def _confidence_scale(model_meta: Any) -> float:
    """``b0`` from the ``tdfd.model`` metadata (learned: ``confidence_scale``; analytic: ``rel_error_scale``)."""
    if isinstance(model_meta, dict):
        for key in ("confidence_scale", "rel_error_scale"):
            value = model_meta.get(key)
            if isinstance(value, (int, float)) and value > 0:
                return float(value)
    return 0.01


def suggested_min_confidence(estimator: Any) -> float:
    """The ROI-confidence threshold below which the autofocus loop should not trust ``estimator``.

    Confidence scales differ: the analytic estimator's is ``1 / (1 + (rel / 0.03)^2)`` of its
    predicted relative error, the learned model's ``1 / (1 + (b / 0.01)^2)`` of a Laplace
    scale (tdfd.model). Estimators may carry their own ``min_confidence``; default 0.01.
    """
    return float(getattr(estimator, "min_confidence", 0.01))


def estimator_breathing(estimator: Any) -> float:
    """The focus breathing ``m`` (1/dpt) an estimator registers its pairs for (0: none): an
    :class:`OnnxEstimator` whose model registers it, or a
    :class:`~tdfd.autofocus.registered.BreathingRegistered` wrapper."""
    return float(getattr(estimator, "magnification_per_dpt", 0.0) or 0.0)


def suggested_confidence_scale(estimator: Any) -> float:
    """The estimator's ``b0``: the predicted relative inverse-depth error at which its confidence is 0.5.

    The learned model's confidence is ``1 / (1 + (b / b0)^2)`` of its Laplace scale ``b``
    (``confidence_scale`` in the ONNX file's ``tdfd.model`` metadata), the analytic one's of
    its predicted relative error (``rel_error_scale``). Estimators may carry their own
    ``confidence_scale``; default 0.01.
    """
    return float(getattr(estimator, "confidence_scale", 0.01))


class OnnxEstimator:
    """The exported DFD model (one ``.onnx`` file, CONTRACT.md section 2) through
    :class:`tdfd.runtime.DepthRuntime` (numpy and onnxruntime only; no torch).

    The runtime checks every pair (:func:`tdfd.pair_check.pair_problem`): a pair that is no
    DFD pair (identical, black or saturated frames) comes back with zero confidence, and its
    reason is kept in :attr:`last_problem` for callers outside the autofocus loop (the DFD
    policy checks the whole frames itself before it asks for an estimate, and reports a
    capture fault).

    Args:
        path: the ONNX file (default: :func:`default_model_path`).
        threads: onnxruntime intra-op threads.
        camera: the user's camera (a :class:`~tdfd.camera.Camera`, preset name or camera
            JSON), checked against the model's coverage at load time
            (``DepthRuntime(..., camera=...)``); default: the model's own.

    Attributes:
        camera: the user's camera, else the one from the ``tdfd.camera`` metadata.
        tile, stride: from ``tdfd.grid``.
        path: the file.
        backend: ``"tdfd.runtime"``.
        last_problem: why the last pair was no DFD pair, or ``None``.
        takes_optical_centre: ``True``: a crop's ``optical_centre`` is passed on to the
            runtime, which moves each frame by its breathing translation when the model
            registers breathing (``DepthRuntime(..., optical_centre=)``).
        min_confidence: suggested ROI-confidence threshold for autofocus (see
            :func:`suggested_min_confidence`), tuned on the bench with the reference model
            on targets apart from the benchmark's.

    Raises:
        ModelError: the file is missing or lacks the contract's inputs, outputs or metadata,
            or it does not cover ``camera``.
        CameraError: a ``camera`` file that is missing or invalid.
    """

    backend = "tdfd.runtime"
    takes_optical_centre = True

    def __init__(self, path: str | Path | None = None, threads: int = ONNX_INTRA_THREADS,
                 camera: Camera | str | Path | None = None) -> None:
        self.path = Path(path) if path is not None else default_model_path()
        self.threads = int(threads)
        self.min_confidence = 0.003
        if not self.path.is_file():
            raise ModelError(f"ONNX model {self.path} not found")
        self._runtime = DepthRuntime(self.path, threads=self.threads, camera=camera)
        self.camera: Camera = self._runtime.camera
        self.tile, self.stride = int(self._runtime.tile), int(self._runtime.stride)
        self.last_problem: str | None = None
        self.confidence_scale = _confidence_scale(self._runtime.metadata.get(MODEL_KEY))

    @property
    def magnification_per_dpt(self) -> float:
        """The focus breathing the model registers in its graph (``tdfd.breathing``; 0: none)."""
        return float(self._runtime.magnification_per_dpt or 0.0)

    @property
    def takes_psf_family(self) -> bool:
        """Whether the model's CNN takes the lens's PSF family (``tdfd.psf_family`` metadata)."""
        return self._runtime.psf_family_info.takes_input

    @property
    def psf_family(self) -> str | None:
        """The PSF family the model is told now (``None``: unknown, or no family input)."""
        return self._runtime.psf_family

    def set_psf_family(self, family: str | None) -> "OnnxEstimator":
        """Tell the model's CNN the lens's PSF family (``"gaussian"``, ``"pillbox"``; ``None``:
        unknown); returns ``self``.

        Raises:
            ModelError: the model has no family input (:attr:`takes_psf_family`).
            InputError: an unknown family.
        """
        self._runtime.set_psf_family(family)
        return self

    def __call__(self, image_f1: np.ndarray, image_f2: np.ndarray,
                 optical_centre: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Depth (m) and confidence, each ``(h, w)``, for one pair of ``(H, W)`` frames
        (``optical_centre``: where the optical centre lies in them, when they are a crop)."""
        centre = optical_centre if self._runtime.magnification_per_dpt else None  # no breathing: nothing to move
        res = self._runtime(_as_frame(image_f1, "image_f1"), _as_frame(image_f2, "image_f2"), optical_centre=centre,
                            pooled=False)  # each tile's own estimate: the ROI pools them
        self.last_problem = res.problem
        depth, conf = res.depth, res.confidence
        return np.asarray(depth, np.float32).reshape(np.shape(depth)[-2:]), np.asarray(conf, np.float32).reshape(np.shape(conf)[-2:])

    def __repr__(self) -> str:
        return f"OnnxEstimator({str(self.path)!r}, tile={self.tile}, stride={self.stride}, backend={self.backend!r})"


class AnalyticEstimator:
    """The analytic Fourier-ratio DFD (torch), as an estimator for the autofocus loop.

    Args:
        camera: camera description (default ``reference``).
        tile, stride: tile grid (px).
        threads: torch intra-op threads during a call (restored afterwards); one thread is
            faster than two for these small frames and immune to a busy machine.
        **kwargs: passed to :class:`tdfd.dfd.FourierRatioDFD`.
    """

    def __init__(self, camera: Camera | None = None, tile: int = 64, stride: int = 32, threads: int | None = 1,
                 **kwargs: Any) -> None:
        import torch

        from ..dfd.fourier_ratio import FourierRatioDFD

        self.camera = camera if camera is not None else Camera.preset("reference")
        self.tile, self.stride = int(tile), int(stride)
        self._torch = torch
        self._model = FourierRatioDFD(self.camera, tile=self.tile, stride=self.stride, **kwargs).eval()
        self.threads = threads
        self.min_confidence = 0.005
        self.confidence_scale = float(getattr(self._model, "rel_error_scale", 0.03))
        self.backend = "torch (analytic FourierRatioDFD)"

    def __call__(self, image_f1: np.ndarray, image_f2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        torch = self._torch
        a = torch.from_numpy(_as_frame(image_f1, "image_f1").copy())
        b = torch.from_numpy(_as_frame(image_f2, "image_f2").copy())
        with torch.no_grad(), torch_threads(self.threads):
            depth, conf = self._model(a, b)
        return depth[0, 0].numpy(), conf[0, 0].numpy()

    def __repr__(self) -> str:
        return f"AnalyticEstimator(tile={self.tile}, stride={self.stride})"


def load_estimator(spec: str | None = None) -> OnnxEstimator | AnalyticEstimator:
    """An estimator from a spec: a path to an ``.onnx`` file, ``"analytic"``, or ``None``/``"auto"``.

    ``None``/``"auto"``: the shipped model if it exists, else the analytic stand-in (with a
    warning).

    Raises:
        ModelError: a named ONNX file is missing or invalid.
    """
    if spec in (None, "", "auto"):
        path = default_model_path()
        if path.is_file():
            return OnnxEstimator(path)
        log.info("shipped model %s not found: using the analytic Fourier-ratio estimator as a stand-in", path)
        return AnalyticEstimator()
    if spec == "analytic":
        return AnalyticEstimator()
    return OnnxEstimator(spec)
