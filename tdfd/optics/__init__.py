"""Optics: thin-lens defocus geometry, PSFs/OTFs and defocus rendering."""

from .thin_lens import *  # noqa: F401,F403
from .thin_lens import __all__ as _thin_all

__all__ = list(_thin_all)
