r"""Depth from defocus on the device: an ONNX Runtime session around the exported model.

Needs only numpy and onnxruntime (no torch): a device ships this module, ``tdfd/camera.py``,
``tdfd/errors.py`` and one ``.onnx`` file (``CONTRACT.md`` section 2). The camera and the
tile grid are read from the file's metadata. ``DepthRuntime(..., camera=CAM)`` names the
user's own camera (a :class:`~tdfd.camera.Camera`, a preset name or a camera JSON file):
it is checked at load time against the model's ``tdfd.coverage`` metadata
(:mod:`tdfd.coverage`) and a camera the model does not serve is refused.

Inputs are validated before they reach the session, with typed errors
(:mod:`tdfd.errors`): ``float16/32/64`` arrays must hold linear intensity in ``[0, 1]``;
``uint8``/``uint16`` arrays are divided by a white level (default ``255``/``65535``, so pass
``white_level=4095`` for 12-bit data stored in 16-bit words). Arrays may be ``(H, W)``,
``(1, H, W)`` or ``(N, 1, H, W)``; results keep that layout.

Focus breathing: a model exported for a camera that breathes (``tdfd.breathing`` metadata,
:data:`tdfd.contract.BREATHING_KEY`) registers the two frames about the centre of the frames
it is given, which must then be the optical centre. For a region of interest, pass the whole
frames and ``window=(y0, y1, x0, x1)``: the runtime cuts the crop of each frame moved by the
translation that magnification about the optical centre implies there
(:func:`tdfd.breathing.breathing_window`: :func:`~tdfd.breathing.window_shifts`, rounded to
whole pixels as the graph moves whole pixels),
so the window's depths match those of the whole frame. ``optical_centre=(cy, cx)`` names the
optical centre in the given frames' pixels when it is not their centre (a read-out window off
the sensor's centre); default the frames' centre.

PSF family: a model trained with the lens's PSF family as a CNN input carries the
``tdfd.psf_family`` metadata (:data:`tdfd.contract.PSF_FAMILY_KEY`); ``psf_family="pillbox"``
(or ``"gaussian"``, ``"unknown"``) runs the same file told that family
(:mod:`tdfd.runtime_psf_family`); the default keeps the family baked in at export.

Full-resolution resampling (``full_resolution=True``) interpolates the tile grid
bilinearly with each tile's value placed at its centre, pixel
``(i * stride + (tile - 1) / 2, j * stride + (tile - 1) / 2)``; pixels outside the outermost
centres take the nearest centre's value (edge extension). Depth is interpolated in inverse
depth (blur is linear in it), confidence linearly.

Example:
    >>> import numpy as np
    >>> rt = DepthRuntime(default_model_path())  # doctest: +SKIP
    >>> res = rt(frame_f1, frame_f2)  # uint16 (1200, 1600) frames  # doctest: +SKIP
    >>> res.depth.shape, res.centre_depth()  # doctest: +SKIP
    ((36, 49), 0.52)
    >>> rt.in_focus_power_dpt(res.centre_depth())  # ECVFL command in dioptres  # doctest: +SKIP
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .breathing import breathing_window, registration_magnifications
from .camera import Camera, in_focus_power_dpt
from .contract import (BREATHING_KEY, CAMERA_KEY, COVERAGE_KEY, DEFAULT_MODEL_ENV, DEFAULT_MODEL_RELPATH, GRID_KEY, INPUT_NAMES, METADATA_KEYS,
                       OUTPUT_NAMES, PACKAGED_MODEL_RELPATH, POOLED_OUTPUT_NAMES, VERSION_KEY)
from .camera_file import resolve_camera_file
from .coverage import check_coverage
from .errors import DTypeError, InputError, ModelError, ShapeError
from .runtime_psf_family import EXPORTED, code_array, read_psf_family, requested_family
from .frames import raw_to_linear
from .pair_check import pair_problem

__all__ = [
    "DepthRuntime",
    "DepthResult",
    "default_model_path",
    "SHIPPED_MODEL",
    "tile_centres",
    "resample_to_image",
    "in_focus_power_dpt",
    "make_session",
    "check_pairs",
    "DEFAULT_MODEL_ENV",
    "DEFAULT_OPTIMIZATION",
    "DEFAULT_CONFIDENCE_THRESHOLD",
    "INPUT_NAMES",
    "OUTPUT_NAMES",
]

logger = logging.getLogger(__name__)

#: Confidence at which a cell counts as valid by default. For the shipped reference model
#: (confidence ``1 / (1 + (b / 0.01)^2)``, ``b`` the predicted Laplace scale of the relative
#: error) 0.1 means ``b`` of about 3 %; on held-out planes its tiles above 0.1 have a median
#: error of 1.6 % and texture-less tiles stay below 0.01 (``models/reference_report.md``).
DEFAULT_CONFIDENCE_THRESHOLD = 0.1


#: The model shipped inside the package (package data; in a source checkout a link to
#: ``models/reference.onnx``).
SHIPPED_MODEL = Path(__file__).resolve().parent / PACKAGED_MODEL_RELPATH


def default_model_path() -> Path:
    """The model used when none is given.

    Looked up in order: ``$TDFD_MODEL``; the model shipped in the package,
    ``tdfd/assets/reference.onnx`` (installed as package data by ``pip install``; in a
    source checkout a link to ``models/reference.onnx``, which is returned); then
    ``models/reference.onnx`` in the working directory.

    Raises:
        ModelError: none of them exists (one line: where it looked and how to name a model).
    """
    env = os.environ.get(DEFAULT_MODEL_ENV)
    if env:
        p = Path(env).expanduser()
        if not p.is_file():
            raise ModelError(f"${DEFAULT_MODEL_ENV} names {p}, which does not exist")
        return p
    candidates = [SHIPPED_MODEL, Path.cwd() / DEFAULT_MODEL_RELPATH]
    for p in candidates:
        if p.is_file():
            return p.resolve()
    raise ModelError("no model found: name one with --model PATH (Python: model_path=) or $TDFD_MODEL (looked for "
                     + ", ".join(str(c) for c in candidates) + ")")


def tile_centres(height: int, width: int, tile: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (rows, columns) of the tile centres of an ``height`` x ``width`` image."""
    h, w = (height - tile) // stride + 1, (width - tile) // stride + 1
    return np.arange(h) * stride + (tile - 1) / 2.0, np.arange(w) * stride + (tile - 1) / 2.0


def _interp_weights(n_out: int, n_grid: int, tile: int, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    u = (np.arange(n_out, dtype=np.float64) - (tile - 1) / 2.0) / stride
    u = np.clip(u, 0.0, n_grid - 1)
    i0 = np.minimum(np.floor(u).astype(np.intp), max(n_grid - 2, 0))
    i1 = np.minimum(i0 + 1, n_grid - 1)
    return i0, i1, (u - i0)


def _interp_matrix(n_out: int, n_grid: int, tile: int, stride: int) -> np.ndarray:
    i0, i1, f = _interp_weights(n_out, n_grid, tile, stride)
    m = np.zeros((n_out, n_grid), np.float64)
    rows = np.arange(n_out)
    np.add.at(m, (rows, i0), 1.0 - f)
    np.add.at(m, (rows, i1), f)
    return m.astype(np.float32)


def resample_to_image(grid: np.ndarray, height: int, width: int, tile: int, stride: int) -> np.ndarray:
    """Bilinear, tile-centre-aligned resampling of ``(..., h, w)`` maps to ``(..., H, W)`` float32.

    Cell ``(i, j)`` sits at pixel ``(i * stride + (tile - 1) / 2, j * stride + (tile - 1) / 2)``;
    beyond the outermost centres the edge values extend (no extrapolation). Computed as
    ``A_y @ grid @ A_x^T`` with the (sparse) interpolation matrices, about 2 ms for a
    1200 x 1600 map.
    """
    g = np.asarray(grid, dtype=np.float32)
    lead, (h, w) = g.shape[:-2], g.shape[-2:]
    ay = _interp_matrix(height, h, tile, stride)
    ax = np.ascontiguousarray(_interp_matrix(width, w, tile, stride).T)
    flat = g.reshape(-1, h, w)
    out = np.empty((flat.shape[0], height, width), np.float32)
    for i in range(flat.shape[0]):
        np.matmul(ay @ flat[i], ax, out=out[i])
    return out.reshape(*lead, height, width)


@dataclass
class DepthResult:
    """Output of :class:`DepthRuntime`.

    Arrays follow the input layout: ``(h, w)`` for ``(H, W)`` input, ``(1, h, w)`` for
    ``(1, H, W)``, ``(N, 1, h, w)`` for ``(N, 1, H, W)``; with ``full_resolution`` the last two
    axes are ``(H, W)`` instead of the tile grid.

    Attributes:
        depth: refined object distance in metres, float32.
        confidence: in [0, 1], float32.
        depth_analytic: analytic Fourier-ratio depth in metres, float32.
        image_size: ``(H, W)`` of the input frames in pixels.
        tile, stride: the tile grid in pixels.
        full_resolution: whether the maps were resampled to ``(H, W)``.
        problems: per pair (in batch order), why it is no DFD pair
            (:func:`tdfd.pair_check.pair_problem`, e.g. ``"frames are identical: the lens did
            not move"``) or ``None``; a pair with a problem has confidence 0 everywhere.
        depth_pooled, confidence_pooled: the depth map pooled along the scene's depth structure
            and its confidence (:data:`tdfd.contract.POOLED_OUTPUT_NAMES`), from a file with that
            stage and a call that asked for it; ``None`` otherwise. ``depth`` and ``confidence``
            are each tile's own estimate either way.
    """

    depth: np.ndarray
    confidence: np.ndarray
    depth_analytic: np.ndarray
    image_size: tuple[int, int]
    tile: int
    stride: int
    full_resolution: bool = False
    problems: tuple[str | None, ...] = ()
    depth_pooled: np.ndarray | None = None
    confidence_pooled: np.ndarray | None = None

    @property
    def depth_map(self) -> tuple[np.ndarray, np.ndarray]:
        """``(depth, confidence)`` of the best depth map: the pooled one when present, else the tiles'."""
        if self.depth_pooled is not None and self.confidence_pooled is not None:
            return self.depth_pooled, self.confidence_pooled
        return self.depth, self.confidence

    @property
    def problem(self) -> str | None:
        """The capture problem of a single pair (of the first pair with one in a batch), or ``None``."""
        return next((p for p in self.problems if p), None)

    @property
    def grid_shape(self) -> tuple[int, int]:
        """Tile-grid shape ``(h, w)`` of the input image size."""
        H, W = self.image_size
        return (H - self.tile) // self.stride + 1, (W - self.tile) // self.stride + 1

    def valid(self, threshold: float = DEFAULT_CONFIDENCE_THRESHOLD) -> np.ndarray:
        """Boolean mask of cells (or pixels) whose confidence is at least ``threshold``."""
        return self.confidence >= threshold

    def valid_fraction(self, threshold: float = DEFAULT_CONFIDENCE_THRESHOLD) -> float:
        """Fraction of cells (or pixels) whose confidence is at least ``threshold``."""
        return float(np.mean(self.valid(threshold)))

    def _centre_mask(self, fraction: float) -> np.ndarray:
        H, W = self.image_size
        if self.full_resolution:
            ys, xs = np.arange(H) + 0.5, np.arange(W) + 0.5
        else:
            ys, xs = tile_centres(H, W, self.tile, self.stride)
            ys, xs = ys + 0.5, xs + 0.5
        iny = np.abs(ys - H / 2.0) < fraction * H / 2.0
        inx = np.abs(xs - W / 2.0) < fraction * W / 2.0
        if not iny.any():  # always keep the middle row / column
            iny[np.argmin(np.abs(ys - H / 2.0))] = True
        if not inx.any():
            inx[np.argmin(np.abs(xs - W / 2.0))] = True
        return iny[:, None] & inx[None, :]

    def at_full_resolution(self) -> "DepthResult":
        """This result resampled to the image size (see the module notes on alignment)."""
        if self.full_resolution:
            return self
        H, W = self.image_size
        up = lambda x: resample_to_image(x, H, W, self.tile, self.stride)  # noqa: E731
        pooled = self.depth_pooled is not None and self.confidence_pooled is not None
        return DepthResult(depth=1.0 / up(1.0 / self.depth), confidence=up(self.confidence),
                           depth_analytic=1.0 / up(1.0 / self.depth_analytic), image_size=self.image_size,
                           tile=self.tile, stride=self.stride, full_resolution=True, problems=self.problems,
                           depth_pooled=1.0 / up(1.0 / self.depth_pooled) if pooled else None,
                           confidence_pooled=up(self.confidence_pooled) if pooled else None)

    def centre_depth(self, fraction: float = 0.5, threshold: float = DEFAULT_CONFIDENCE_THRESHOLD) -> float | np.ndarray:
        """Median depth (metres) of the confident cells in the centre region.

        The centre region holds the cells (or pixels) whose centres lie strictly inside the
        middle ``fraction`` of the image height and width (at least the cells nearest the
        image centre).

        Returns:
            A float for a single image, else an ``(N,)`` array; ``nan`` where no cell of the
            centre region reaches ``threshold``.
        """
        if not 0 < fraction <= 1:
            raise InputError(f"fraction must be in (0, 1], got {fraction}")
        mask = self._centre_mask(fraction)
        d = self.depth.reshape(-1, *self.depth.shape[-2:])
        c = self.confidence.reshape(-1, *self.confidence.shape[-2:])
        out = np.array([float(np.median(di[mask & (ci >= threshold)])) if np.any(mask & (ci >= threshold))
                        else math.nan for di, ci in zip(d, c)])
        return float(out[0]) if self.depth.ndim <= 3 and out.size == 1 else out


def _as_images(name: str, image: Any, white_level: float | None) -> tuple[np.ndarray, tuple[int, ...]]:
    """Validate one input and return it as float32 ``(N, 1, H, W)`` plus its original shape."""
    if not isinstance(image, np.ndarray):
        raise DTypeError(f"{name} must be a numpy array, got {type(image).__name__}")
    shape = image.shape
    if image.ndim == 2:
        arr = image[None, None]
    elif image.ndim == 3 and shape[0] == 1:
        arr = image[None]
    elif image.ndim == 4 and shape[1] == 1:
        arr = image
    else:
        raise ShapeError(f"{name} must be (H, W), (1, H, W) or (N, 1, H, W) single-channel, got shape {shape}")
    if arr.size == 0:
        raise ShapeError(f"{name} is empty (shape {shape})")
    return raw_to_linear(arr, white_level, name), shape


def check_pairs(image_f1: np.ndarray, image_f2: np.ndarray,
                confidence: np.ndarray) -> tuple[np.ndarray, tuple[str | None, ...]]:
    """Zero the confidence of the pairs that are no DFD pairs (:func:`tdfd.pair_check.pair_problem`).

    Args:
        image_f1, image_f2: float32 ``(N, 1, H, W)`` in [0, 1] (as :meth:`DepthRuntime.prepare` returns).
        confidence: ``(N, 1, h, w)`` model confidence.

    Returns:
        The confidence (a copy where a pair has a problem) and the ``N`` problems (``None`` for a good pair).
    """
    problems = tuple(pair_problem(image_f1[i], image_f2[i]) for i in range(image_f1.shape[0]))
    if any(problems):
        confidence = np.array(confidence, dtype=np.float32, copy=True)
        for i, p in enumerate(problems):
            if p:
                confidence[i] = 0.0
                logger.warning("pair %d is no DFD pair (%s): confidence set to 0", i, p)
    return confidence, problems


#: ONNX Runtime graph optimisation levels by name.
OPTIMIZATION_LEVELS = ("all", "extended", "basic", "disable")
#: The level :class:`DepthRuntime` uses by default (fastest for this model on CPU, see
#: ``docs/BENCHMARKS.md``).
DEFAULT_OPTIMIZATION = "extended"


def make_session(model_path: str | os.PathLike, threads: int = 2, optimization: str = DEFAULT_OPTIMIZATION,
                 providers: Sequence[str] | None = None, initializers: dict[str, np.ndarray] | None = None) -> Any:
    """An ``onnxruntime.InferenceSession`` with ``threads`` intra-op threads (one inter-op).

    ``initializers`` replace the values of graph initializers of those names (same shape and
    dtype; the session keeps the arrays alive).

    Raises:
        ModelError: the file is missing or onnxruntime cannot load it.
        InputError: bad ``threads`` or ``optimization``.
    """
    import onnxruntime as ort

    path = Path(model_path)
    if not path.is_file():
        raise ModelError(f"model file {path} does not exist")
    if int(threads) < 1:
        raise InputError(f"threads must be >= 1, got {threads}")
    levels = dict(zip(OPTIMIZATION_LEVELS, (ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
                                            ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
                                            ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
                                            ort.GraphOptimizationLevel.ORT_DISABLE_ALL)))
    if optimization not in levels:
        raise InputError(f"optimization must be one of {list(OPTIMIZATION_LEVELS)}, got {optimization!r}")
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.graph_optimization_level = levels[optimization]
    arrays = {name: np.ascontiguousarray(a) for name, a in (initializers or {}).items()}
    values = [(name, ort.OrtValue.ortvalue_from_numpy(a), a) for name, a in arrays.items()]  # OrtValues borrow `a`
    for name, value, _ in values:
        so.add_initializer(name, value)
    try:
        session = ort.InferenceSession(str(path), so, providers=list(providers or ["CPUExecutionProvider"]))
        session._tdfd_initializers = values  # the OrtValues must outlive the session
        return session
    except Exception as exc:  # onnxruntime raises its own exception types
        first = str(exc).splitlines()[0] if str(exc) else repr(exc)
        raise ModelError(f"onnxruntime cannot load {path}: {first}") from exc


class DepthRuntime:
    """Run an exported tdfd model with ONNX Runtime (CPU by default, no torch).

    Args:
        model_path: the ``.onnx`` file; ``None`` takes :func:`default_model_path`.
        threads: intra-op threads of the session.
        providers: ONNX Runtime execution providers (default CPU).
        optimization: ONNX Runtime graph optimisation level: ``"all"``, ``"extended"``
            (default), ``"basic"`` or ``"disable"``.
        camera: the user's camera (a :class:`tdfd.Camera`, a preset name or a camera JSON
            file), checked against the model's ``tdfd.coverage``; ``None``: the model's own.
        psf_family: the lens PSF family the CNN is told (:mod:`tdfd.runtime_psf_family`):
            ``"exported"`` (default: the one baked in at export), ``"gaussian"``, ``"pillbox"``,
            or ``"unknown"``/``None``; only for a model with the family input.

    Raises:
        ModelError: a missing, unreadable or non-conforming file (wrong inputs/outputs,
            missing or invalid ``tdfd.*`` metadata), or a ``camera`` the model does not
            cover (or a model that states no coverage).
        CameraError: a ``camera`` file that is missing or invalid (naming it).
        InputError: a ``psf_family`` that is none of those values.

    Attributes:
        camera: the user's ``camera`` when given (it blurs like the model's, so the model's
            depths are its depths, up to :attr:`inverse_depth_offset_dpt`; in-focus powers use
            its own lenses), else :attr:`model_camera`.
        model_camera: :class:`tdfd.Camera` rebuilt from the ``tdfd.camera`` metadata.
        inverse_depth_offset_dpt: ``q_model - q_camera`` (1/m) for a ``camera`` that blurs like
            the model's at inverse depths shifted by a constant (another fixed-lens power:
            :func:`tdfd.coverage.check_coverage`); the returned depths are the camera's
            (``1 / (1/depth_model - offset)``, kept in its extended range ``[1/(2 far), 2/near]``
            1/m, confidence 0 where the shift leaves it). 0.0 otherwise.
        tile, stride: the tile grid (``tdfd.grid``).
        version: the tdfd version that exported the file.
        metadata: all ``metadata_props``, JSON-decoded where possible.
        magnification_per_dpt: the focus breathing the graph registers (``tdfd.breathing``;
            0 when the file states none).
        frame_scales: the two frames' image scales ``(s1, s2)`` it assumes (``(1, 1)``: none).
        psf_family_info: the file's ``tdfd.psf_family`` (:class:`~tdfd.runtime_psf_family.PsfFamilyInfo`).
        psf_family: the family the CNN is told now (``None``: unknown or no family input).
    """

    def __init__(self, model_path: str | os.PathLike | None = None, threads: int = 2,
                 providers: Sequence[str] | None = None, optimization: str = DEFAULT_OPTIMIZATION,
                 camera: Camera | str | os.PathLike | None = None, psf_family: str | None = EXPORTED) -> None:
        path = default_model_path() if model_path is None else Path(model_path)
        self.path = path
        self.threads = int(threads)
        self._session_options = (optimization, providers)
        self.session = make_session(path, threads, optimization, providers)
        inputs = [i.name for i in self.session.get_inputs()]
        outputs = [o.name for o in self.session.get_outputs()]
        if tuple(inputs) != INPUT_NAMES or tuple(outputs) not in (OUTPUT_NAMES, OUTPUT_NAMES + POOLED_OUTPUT_NAMES):
            raise ModelError(f"{path} has inputs {inputs} and outputs {outputs}; expected {list(INPUT_NAMES)} and "
                             f"{list(OUTPUT_NAMES)} (then optionally {list(POOLED_OUTPUT_NAMES)})")
        #: whether the file has the structure-pooled depth map (:data:`tdfd.contract.POOLED_OUTPUT_NAMES`)
        self.has_pooled = len(outputs) > len(OUTPUT_NAMES)
        raw = self.session.get_modelmeta().custom_metadata_map
        self.metadata: dict[str, Any] = {}
        for key, value in raw.items():
            try:
                self.metadata[key] = json.loads(value)
            except (json.JSONDecodeError, TypeError):
                self.metadata[key] = value
        for key in METADATA_KEYS:
            if key not in self.metadata:
                raise ModelError(f"{path} lacks the {key!r} metadata; export it with `python -m export`")
        try:
            self.camera = Camera.from_dict(self.metadata[CAMERA_KEY], name=path.stem)
        except Exception as exc:
            raise ModelError(f"{path}: invalid 'tdfd.camera' metadata: {exc}") from exc
        grid = self.metadata[GRID_KEY]
        try:
            self.tile, self.stride = int(grid["tile"]), int(grid["stride"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"{path}: invalid 'tdfd.grid' metadata {grid!r}") from exc
        if self.tile < 1 or not 1 <= self.stride <= self.tile:
            raise ModelError(f"{path}: invalid tile grid tile={self.tile}, stride={self.stride}")
        self.version = str(self.metadata[VERSION_KEY])
        self.magnification_per_dpt, self.frame_scales = self._breathing()
        self.psf_family_info = read_psf_family(self.metadata, str(path))
        self.psf_family: str | None = self.psf_family_info.exported
        if psf_family != EXPORTED:
            self.set_psf_family(psf_family)
        self.model_camera = self.camera
        self.inverse_depth_offset_dpt = 0.0
        if camera is not None:
            self.camera = self._covered_camera(camera)

    def set_psf_family(self, psf_family: str | None) -> "DepthRuntime":
        """Tell the CNN another lens PSF family (values as the constructor's ``psf_family``);
        the session is rebuilt with the family's code when it changes. Returns ``self``.

        Raises:
            InputError: an unknown value.
            ModelError: a model without the family input (``tdfd.psf_family`` metadata).
        """
        family = requested_family(psf_family, self.psf_family_info, str(self.path))
        if family != self.psf_family:
            optimization, providers = self._session_options
            self.session = make_session(self.path, self.threads, optimization, providers,
                                        initializers={self.psf_family_info.initializer: code_array(family)})
            self.psf_family = family
        return self

    def _breathing(self) -> tuple[float, tuple[float, float]]:
        """``(magnification_per_dpt, frame_scales)`` from the ``tdfd.breathing`` metadata."""
        info = self.metadata.get(BREATHING_KEY)
        if info is None:
            return 0.0, (1.0, 1.0)
        try:
            m = float(info["magnification_per_dpt"])
            s1, s2 = (float(v) for v in info["frame_scales"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"{self.path}: invalid {BREATHING_KEY!r} metadata {info!r}") from exc
        if not all(math.isfinite(v) and 0.5 < v < 2.0 for v in (s1, s2)) or not math.isfinite(m):
            raise ModelError(f"{self.path}: implausible {BREATHING_KEY!r} metadata {info!r}")
        return m, (s1, s2)

    def _covered_camera(self, camera: Camera | str | os.PathLike) -> Camera:
        """The user's camera after the load-time coverage check (:mod:`tdfd.coverage`)."""
        label = None
        if not isinstance(camera, Camera):
            label = os.fspath(camera)
            cf = resolve_camera_file(label)
            camera = cf.camera
            if not math.isclose(cf.magnification_per_dpt, self.magnification_per_dpt, rel_tol=0.05, abs_tol=1e-5):
                logger.warning("%s: the camera's magnification_per_dpt %g differs from the %g the model registers; "
                               "export the model for it: python -m export --weights MODEL --camera %s", label,
                               cf.magnification_per_dpt, self.magnification_per_dpt, label)
        if COVERAGE_KEY not in self.metadata:
            raise ModelError(f"{self.path} states no {COVERAGE_KEY!r} (which cameras it covers), so it cannot be "
                             f"checked for camera {camera.name!r}; re-export it with `python -m export`")
        self.inverse_depth_offset_dpt = check_coverage(self.model_camera, self.metadata[COVERAGE_KEY], camera,
                                                       str(self.path), label)
        if self.inverse_depth_offset_dpt:
            logger.info("%s serves camera %r with its inverse depth shifted by %+.4f 1/m (another fixed-lens power)",
                        self.path, camera.name, -self.inverse_depth_offset_dpt)
        return camera

    def _to_camera_depth(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The model's depth as the user's camera's (:mod:`tdfd.coverage`: ``q = q_model -
        inverse_depth_offset_dpt``), in that camera's extended range ``[1/(2 far), 2/near]``
        1/m as the model keeps its own, and the mask of tiles the shift takes outside it."""
        near, far = self.camera.depth_range_m
        q = 1.0 / np.asarray(depth, np.float64) - self.inverse_depth_offset_dpt
        lo, hi = 1.0 / (2.0 * far), 2.0 / near
        return (1.0 / np.clip(q, lo, hi)).astype(np.float32), (q < lo) | (q > hi)

    def __repr__(self) -> str:
        return f"DepthRuntime({str(self.path)!r}, tile={self.tile}, stride={self.stride}, threads={self.threads})"

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        """Tile-grid shape ``(h, w)`` for a ``height`` x ``width`` image."""
        if height < self.tile or width < self.tile:
            raise ShapeError(f"image {height}x{width} is smaller than one {self.tile}x{self.tile} tile")
        return (height - self.tile) // self.stride + 1, (width - self.tile) // self.stride + 1

    def prepare(self, image_f1: np.ndarray, image_f2: np.ndarray,
                white_level: float | None = None) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
        """Validate a pair and return float32 ``(N, 1, H, W)`` arrays in [0, 1] and the input shape.

        Raises:
            DTypeError: not a numpy array, unsupported dtype, or the two dtypes differ.
            ShapeError: not single-channel ``(H, W)``/``(1, H, W)``/``(N, 1, H, W)``, shapes
                differ, or smaller than one tile.
            NonFiniteError: NaN or inf.
            RangeError: float values outside [0, 1], integer values above the white level, or
                a non-positive white level.
        """
        for name, im in (("image_f1", image_f1), ("image_f2", image_f2)):
            if not isinstance(im, np.ndarray):
                raise DTypeError(f"{name} must be a numpy array, got {type(im).__name__}")
        if image_f1.dtype != image_f2.dtype:
            raise DTypeError(f"image_f1 is {image_f1.dtype} but image_f2 is {image_f2.dtype}; both frames must have one dtype")
        if image_f1.shape != image_f2.shape:
            raise ShapeError(f"image_f1 {image_f1.shape} and image_f2 {image_f2.shape} differ in shape")
        a, shape = _as_images("image_f1", image_f1, white_level)
        b, _ = _as_images("image_f2", image_f2, white_level)
        self.grid_shape(a.shape[-2], a.shape[-1])
        return np.ascontiguousarray(a), np.ascontiguousarray(b), shape

    def run(self, image_f1: np.ndarray, image_f2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The bare session call on float32 ``(N, 1, H, W)`` arrays (no validation, no pair check).

        Raises:
            ModelError: onnxruntime failed (the message names the model and the first line of
                onnxruntime's own).
        """
        return self._session_run(list(OUTPUT_NAMES), image_f1, image_f2)  # type: ignore[return-value]

    def run_pooled(self, image_f1: np.ndarray, image_f2: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`run` with the pooled map after the contract's three outputs:
        ``(depth, confidence, depth_analytic, depth_pooled, confidence_pooled)``.

        Raises:
            ModelError: the file has no pooled outputs (:attr:`has_pooled`), or onnxruntime failed.
        """
        if not self.has_pooled:
            raise ModelError(f"{self.path.name} has no {list(POOLED_OUTPUT_NAMES)} outputs (a model without the "
                             "structure pooling)")
        return self._session_run(list(OUTPUT_NAMES + POOLED_OUTPUT_NAMES), image_f1, image_f2)  # type: ignore

    def run_all(self, image_f1: np.ndarray, image_f2: np.ndarray) -> tuple[np.ndarray, ...]:
        """Every output of the graph (:meth:`run_pooled` for a file with the pooled map, else :meth:`run`)."""
        return self.run_pooled(image_f1, image_f2) if self.has_pooled else self.run(image_f1, image_f2)

    def _session_run(self, names: list[str], image_f1: np.ndarray, image_f2: np.ndarray) -> tuple[np.ndarray, ...]:
        try:
            out = self.session.run(names, {INPUT_NAMES[0]: image_f1, INPUT_NAMES[1]: image_f2})
        except Exception as exc:  # onnxruntime raises its own exception types (Fail, InvalidArgument, ...)
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else repr(exc)
            raise ModelError(f"onnxruntime failed running {self.path.name}: {first}") from exc
        return tuple(out)

    def window_pair(self, image_f1: np.ndarray, image_f2: np.ndarray, window: tuple[int, int, int, int],
                    optical_centre: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The crops ``window = (y0, y1, x0, x1)`` of a prepared pair (float32 ``(N, 1, H, W)``),
        frame by frame moved by the breathing translation at the window's position
        (:func:`tdfd.breathing.window_shifts`), so that the graph's registration about the
        crop's centre equals registration of the whole frames about ``optical_centre``
        (default: the frames' centre). Without breathing: the plain crops.

        Raises:
            ShapeError: the window is not inside the frames or smaller than one tile.
            NonFiniteError: a non-finite ``optical_centre``.
        """
        H, W = image_f1.shape[-2:]
        try:
            y0, y1, x0, x1 = (int(v) for v in window)
        except (TypeError, ValueError):
            raise ShapeError(f"window must be (y0, y1, x0, x1) pixels, got {window!r}") from None
        if not (0 <= y0 < y1 <= H and 0 <= x0 < x1 <= W):
            raise ShapeError(f"window {tuple(window)} is empty or not inside the {H}x{W} frames")
        self.grid_shape(y1 - y0, x1 - x0)
        out = breathing_window(image_f1, image_f2, (y0, y1, x0, x1), registration_magnifications(self.frame_scales),
                               optical_centre)
        return tuple(np.ascontiguousarray(o, dtype=np.float32) for o in out)  # type: ignore

    def __call__(self, image_f1: np.ndarray, image_f2: np.ndarray, white_level: float | None = None,
                 full_resolution: bool = False, window: tuple[int, int, int, int] | None = None,
                 optical_centre: tuple[float, float] | None = None, pooled: bool = True) -> DepthResult:
        """Depth, confidence and analytic depth for a DFD pair.

        Args:
            image_f1: frame at the first ECVFL power: ``(H, W)``, ``(1, H, W)`` or
                ``(N, 1, H, W)``; float in [0, 1], or uint8/uint16.
            image_f2: frame at the second power, same shape and dtype.
            white_level: raw value of full scale; integer frames default to the dtype's
                maximum, float frames to 1.
            full_resolution: resample the maps to ``(H, W)`` (see the module notes).
            window: ``(y0, y1, x0, x1)``: estimate the crop ``[y0:y1, x0:x1]`` of the frames
                only (results on the crop's grid, ``image_size`` the crop's), cut so that a
                breathing model's registration matches that of the whole frames
                (:meth:`window_pair`).
            optical_centre: ``(cy, cx)`` in the given frames' pixels (default their centre);
                with a breathing model, the frames (or the window) are moved accordingly.
            pooled: also return the structure-pooled map (``depth_pooled``,
                ``confidence_pooled``) when the file has it; ``False`` runs the contract's three
                outputs only (what the autofocus reads).

        Returns:
            A :class:`DepthResult` in the input's layout.

        A pair that is no DFD pair (identical frames, a black, much darker or saturated frame:
        :func:`tdfd.pair_check.pair_problem`) gets confidence 0 everywhere and its reason in
        :attr:`DepthResult.problems`.

        Raises:
            DTypeError, ShapeError, NonFiniteError, RangeError: see :meth:`prepare`.
            ModelError: onnxruntime failed.
        """
        a, b, shape = self.prepare(image_f1, image_f2, white_level)
        if window is not None or optical_centre is not None:
            a, b = self.window_pair(a, b, window or (0, a.shape[-2], 0, a.shape[-1]), optical_centre)
        if pooled and self.has_pooled:
            depth, conf, depth_a, depth_p, conf_p = self.run_pooled(a, b)
        else:
            (depth, conf, depth_a), depth_p, conf_p = self.run(a, b), None, None
        if self.inverse_depth_offset_dpt:
            depth, outside = self._to_camera_depth(depth)
            conf = np.where(outside, 0.0, conf).astype(np.float32)  # the shift left the camera's range
            depth_a, _ = self._to_camera_depth(depth_a)
            if depth_p is not None:
                depth_p, outside_p = self._to_camera_depth(depth_p)
                conf_p = np.where(outside_p, 0.0, conf_p).astype(np.float32)
        conf, problems = check_pairs(a, b, conf)
        if conf_p is not None and any(problems):  # the same pairs are no DFD pairs for the pooled map
            conf_p = np.where(np.array([bool(p) for p in problems])[:, None, None, None], 0.0, conf_p).astype(np.float32)
        H, W = a.shape[-2:]
        lead = {2: 0, 3: 1, 4: 2}[len(shape)]  # leading axes to keep: (H, W) -> none, (1, H, W) -> one

        def fmt(x: np.ndarray) -> np.ndarray:
            x = np.asarray(x, dtype=np.float32)
            return x[0, 0] if lead == 0 else (x[0] if lead == 1 else x)

        res = DepthResult(depth=fmt(depth), confidence=fmt(conf), depth_analytic=fmt(depth_a),
                          image_size=(int(H), int(W)), tile=self.tile, stride=self.stride, problems=problems,
                          depth_pooled=None if depth_p is None else fmt(depth_p),
                          confidence_pooled=None if conf_p is None else fmt(conf_p))
        return res.at_full_resolution() if full_resolution else res

    def in_focus_power_dpt(self, depth_m: float | np.ndarray) -> float | np.ndarray:
        """ECVFL power (dioptres) focusing an object at ``depth_m``: ``1/d + 1/d_s - 1/f0``,
        with the camera from the model metadata."""
        return in_focus_power_dpt(self.camera, depth_m)
