"""The public names: every name a package's ``__all__`` lists resolves, and the names its docstring promises are exported."""

from __future__ import annotations

import importlib
import re
import subprocess
import sys

import pytest

PACKAGES = ["tdfd", "tdfd.autofocus", "tdfd.autofocus.sim"]


@pytest.mark.parametrize("package", PACKAGES)
def test_every_name_in_all_resolves(package):
    mod = importlib.import_module(package)
    assert len(mod.__all__) == len(set(mod.__all__)), "duplicate names in __all__"
    missing = [name for name in mod.__all__ if not hasattr(mod, name)]
    assert not missing, f"{package}.__all__ names that do not resolve: {missing}"


@pytest.mark.parametrize("package", PACKAGES)
def test_docstring_names_are_exported(package):
    """``:class:`/:func:`/:data:` references to ``package.Name`` in the docstring are in ``__all__``;
    ``:mod:`` references to ``package.sub`` import."""
    mod = importlib.import_module(package)
    doc = mod.__doc__ or ""
    prefix = re.escape(package) + r"\."
    names = set(re.findall(r":(?:class|func|data):`~?" + prefix + r"(\w+)`", doc))
    names |= {n for n in re.findall(r":(?:class|func|data):`(\w+)`", doc)}  # short references, e.g. :class:`Roi`
    assert not names - set(mod.__all__), f"{package} docstring names not in __all__: {sorted(names - set(mod.__all__))}"
    for sub in re.findall(r":mod:`~?(" + prefix + r"[\w.]+)`", doc):
        importlib.import_module(sub)


def test_fourier_ratio_dfd_is_the_estimator_class():
    import tdfd
    from tdfd.dfd.fourier_ratio import FourierRatioDFD

    assert tdfd.FourierRatioDFD is FourierRatioDFD
    assert "FourierRatioDFD" in dir(tdfd)
    with pytest.raises(AttributeError, match="no attribute 'NoSuchName'"):
        tdfd.NoSuchName  # noqa: B018


def test_import_does_not_load_torch():
    """The ONNX runtime and the hardware loop run without torch: importing the packages must not load it."""
    code = "import sys, tdfd, tdfd.autofocus, tdfd.autofocus.sim, tdfd.autofocus.hardware; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
