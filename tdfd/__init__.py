"""tdfd: motionless depth-from-defocus autofocus with an electrically tunable lens.

Public entry points: :class:`tdfd.Camera`, :class:`tdfd.FourierRatioDFD`, the optics in
:mod:`tdfd.optics`, the lens driver in :mod:`tdfd.driver`.
"""

from __future__ import annotations

import logging

__version__ = "0.1.0"

from .camera import Camera  # noqa: E402
from .errors import *  # noqa: E402,F401,F403

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = ["Camera", "__version__"]
