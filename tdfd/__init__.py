"""tdfd: motionless depth-from-defocus autofocus with an electrically tunable lens.

Public entry points: :class:`tdfd.Camera`, :class:`tdfd.FourierRatioDFD`, the optics in
:mod:`tdfd.optics`, the lens driver in :mod:`tdfd.driver`, the autofocus loop in
:mod:`tdfd.autofocus`; the error types of :mod:`tdfd.errors`.

``import tdfd`` does not import torch (the ONNX runtime and the hardware loop run without
it): :class:`FourierRatioDFD` is loaded on first access.
"""

from __future__ import annotations

import logging
from typing import Any

__version__ = "0.1.0"

from .camera import Camera  # noqa: E402
from .errors import *  # noqa: E402,F401,F403
from .errors import __all__ as _errors_all  # noqa: E402

logging.getLogger(__name__).addHandler(logging.NullHandler())

#: names exported lazily (they import torch): name -> module that defines it.
_LAZY = {"FourierRatioDFD": "tdfd.dfd.fourier_ratio"}

__all__ = ["Camera", "FourierRatioDFD", "__version__", *_errors_all]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'tdfd' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
