"""The ONNX model contract's names, written once (``CONTRACT.md`` section 2).

Torch-free (plain constants): the exporter (``export/``), the device runtime
(:mod:`tdfd.runtime`) and the autofocus estimators all read the graph's input and output
names, the metadata keys and the default model's location from here.

Example:
    >>> INPUT_NAMES, OUTPUT_NAMES[0], METADATA_KEYS[0]
    (('image_f1', 'image_f2'), 'depth', 'tdfd.camera')
"""

from __future__ import annotations

from pathlib import PurePosixPath

__all__ = [
    "INPUT_NAMES",
    "OUTPUT_NAMES",
    "POOLED_OUTPUT_NAMES",
    "CAMERA_KEY",
    "GRID_KEY",
    "VERSION_KEY",
    "MODEL_KEY",
    "COVERAGE_KEY",
    "BREATHING_KEY",
    "PSF_FAMILY_KEY",
    "METADATA_KEYS",
    "MIN_OPSET",
    "DEFAULT_MODEL_ENV",
    "DEFAULT_MODEL_RELPATH",
    "PACKAGED_MODEL_RELPATH",
]

#: Graph inputs, in order: the frames at the first and the second ECVFL power.
INPUT_NAMES: tuple[str, str] = ("image_f1", "image_f2")
#: Graph outputs, in the order the model returns them.
OUTPUT_NAMES: tuple[str, str, str] = ("depth", "confidence", "depth_analytic")
#: Optional graph outputs beyond the contract's three, after them and in this order: the depth
#: map pooled along the scene's depth structure and its confidence, each ``[N, 1, h, w]`` on the
#: same grid (:mod:`tdfd.model.structure_pooling`). Present only in a file whose model has that
#: stage. ``depth`` and ``confidence`` stay each tile's own estimate, independent of its
#: neighbours' (what the autofocus pools); the pooled map is the better depth map.
POOLED_OUTPUT_NAMES: tuple[str, str] = ("depth_pooled", "confidence_pooled")
#: ``metadata_props`` key of the camera description (``Camera.to_dict()`` as JSON).
CAMERA_KEY = "tdfd.camera"
#: ``metadata_props`` key of the tile grid (``{"tile", "stride"}`` as JSON).
GRID_KEY = "tdfd.grid"
#: ``metadata_props`` key of the exporting package version (a JSON string literal).
VERSION_KEY = "tdfd.version"
#: Optional, informational ``metadata_props`` key: the model's full description.
MODEL_KEY = "tdfd.model"
#: Optional ``metadata_props`` key beyond the contract's three: which cameras the model covers
#: (:mod:`tdfd.coverage`; checked when ``DepthRuntime`` is given a camera).
COVERAGE_KEY = "tdfd.coverage"
#: Optional ``metadata_props`` key: the focus breathing the graph registers,
#: ``{"magnification_per_dpt": m, "frame_scales": [s1, s2]}`` (``s = 1 + m P`` at the two ECVFL
#: powers). The graph brings both frames to the scale ``sqrt(s1 s2)`` about the centre of its
#: inputs; a caller cutting an off-centre crop shifts it (:meth:`tdfd.runtime.DepthRuntime.__call__`,
#: ``window=``). Absent: no registration (``m = 0``).
BREATHING_KEY = "tdfd.breathing"
#: Optional ``metadata_props`` key: the lens PSF family the refinement CNN is told,
#: ``{"input": true, "family": "gaussian" | "pillbox" | null, "initializer": NAME}``. ``family`` is
#: what the export baked in (``null``: unknown); ``initializer`` names the graph's ``(1, 2, 1, 1)``
#: float32 code (``[1, 0]`` Gaussian, ``[0, 1]`` pillbox, zeros unknown), which ONNX Runtime may
#: override (:class:`tdfd.runtime.DepthRuntime` ``psf_family``). Absent: the model has no family input.
PSF_FAMILY_KEY = "tdfd.psf_family"
#: The keys every exported file must carry, each value a JSON string.
METADATA_KEYS: tuple[str, str, str] = (CAMERA_KEY, GRID_KEY, VERSION_KEY)
#: Lowest ONNX opset the contract allows.
MIN_OPSET = 18
#: Environment variable naming the default model file.
DEFAULT_MODEL_ENV = "TDFD_MODEL"
#: The shipped model, relative to the repository root (or the working directory).
DEFAULT_MODEL_RELPATH = PurePosixPath("models") / "reference.onnx"
#: The shipped model as package data, relative to the ``tdfd`` package folder (in a checkout a
#: link to :data:`DEFAULT_MODEL_RELPATH`; the wheel holds the file itself).
PACKAGED_MODEL_RELPATH = PurePosixPath("assets") / "reference.onnx"
