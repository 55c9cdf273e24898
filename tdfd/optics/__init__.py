"""Optics: thin-lens defocus geometry, PSFs/OTFs and defocus rendering."""

from .thin_lens import *  # noqa: F401,F403
from .thin_lens import __all__ as _thin_all

__all__ = list(_thin_all)
from .psf import *  # noqa: F401,F403,E402
from .psf import __all__ as _psf_all  # noqa: E402
from .render import *  # noqa: F401,F403,E402
from .render import __all__ as _render_all  # noqa: E402
from .aberrated_psf import PSFModel  # noqa: E402

__all__ += list(_psf_all) + list(_render_all) + ["PSFModel"]
