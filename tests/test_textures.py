"""Procedural textures: shapes, ranges, determinism, parameters, anti-aliasing."""

import math

import pytest
import torch

from tdfd.errors import InputError
from tdfd.textures import (TEXTURE_FAMILIES, apply_albedo, checkers, dead_leaves, dots, flat, fractal, random_texture,
                           register_texture, spectral_tilt, stripes, voronoi)

SIZE = (48, 64)


def _g(seed=0):
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize("name", sorted(TEXTURE_FAMILIES))
def test_every_family_shape_range_and_determinism(name):
    fam = TEXTURE_FAMILIES[name]
    params = fam.sample_params(_g(1), SIZE)
    a = fam.fn(SIZE, _g(2), 2, **params)
    b = fam.fn(SIZE, _g(2), 2, **params)
    c = fam.fn(SIZE, _g(3), 2, **params)
    assert a.shape == (2, 1, *SIZE) and a.dtype == torch.float32
    assert bool(torch.isfinite(a).all()) and float(a.min()) >= 0.0 and float(a.max()) <= 1.0
    assert torch.equal(a, b)  # same generator state, same bytes
    if name != "gradient" or params.get("kind") == "radial":
        assert not torch.equal(a, c)  # a different seed gives a different texture


def test_random_texture_params_and_families():
    tex, p = random_texture(_g(5), 40, families=["stripes", "dots"])
    assert tex.shape == (1, 1, 40, 40)
    assert p["family"] in ("stripes", "dots")
    assert 0 < p["albedo"] <= 1 and 0 < p["contrast"] <= 1
    assert float(tex.max()) <= p["albedo"] + 1e-6
    tex2, p2 = random_texture(_g(5), 40, families=["stripes", "dots"])
    assert torch.equal(tex, tex2) and p == p2
    seen = {random_texture(_g(s), 16)[1]["family"] for s in range(60)}
    assert len(seen) >= 8  # the draw covers the families
    with pytest.raises(InputError):
        random_texture(_g(0), 16, family="photograph")


def test_flat_is_nearly_textureless_and_albedo_sets_level():
    t = flat(64, _g(0), variation=0.01, grain=0.001)
    assert float(t.std()) < 0.01
    r = apply_albedo(t, 0.2, 1.0)
    assert abs(float(r.mean()) - 0.1) < 0.01
    with pytest.raises(InputError):
        apply_albedo(t, 1.5, 0.5)


def test_square_wave_is_box_filtered():
    # the mean coverage equals the duty cycle whatever the period, also below 2 px
    for period, duty in ((8.0, 0.5), (5.3, 0.3), (2.0, 0.25)):
        s = stripes((64, 256), _g(0), period=period, angle=0.0, duty=duty)
        assert float(s.mean()) == pytest.approx(duty, abs=0.02)
    # an edge is at most one partially covered pixel wide
    s = stripes((4, 64), _g(0), period=32.0, angle=0.0, duty=0.5, phase=0.25)[0, 0, 0]
    partial = ((s > 0.01) & (s < 0.99)).sum()
    assert int(partial) <= 4  # four edges in 64 px


def test_checkers_dots_voronoi_dead_leaves_basic_statistics():
    c = checkers(64, _g(0), period=16.0)
    assert float(c.mean()) == pytest.approx(0.5, abs=0.05)
    d = dots(64, _g(0), period=16.0, radius=4.0)
    assert float(d.mean()) == pytest.approx(math.pi * 16 / 256, abs=0.03)
    v = voronoi(64, _g(0), cell=16.0, mode="edges")
    assert 0.3 < float(v.mean()) < 0.95
    leaves = dead_leaves(64, _g(0), leaves=30)
    assert len(torch.unique((leaves * 255).round())) > 10


def test_fractal_spectral_slope():
    x = fractal(128, _g(0), batch=4, beta=2.0)
    spec = torch.fft.rfft2(x - x.mean((-1, -2), keepdim=True)).abs().pow(2).mean((0, 1))
    fy = torch.fft.fftfreq(128)[:, None]
    fx = torch.fft.rfftfreq(128)[None, :]
    f = torch.sqrt(fy ** 2 + fx ** 2)
    lo = spec[(f > 0.02) & (f < 0.04)].mean()
    hi = spec[(f > 0.16) & (f < 0.32)].mean()
    slope = math.log(float(lo / hi)) / math.log(8.0)  # power ratio over 3 octaves
    assert slope == pytest.approx(2.0, abs=0.4)


def _power_slope(x):
    """Log-log slope of the radially averaged power spectrum over 0.02-0.3 cycles/px (least squares over bins)."""
    h, w = x.shape[-2:]
    spec = torch.fft.rfft2((x - x.mean((-1, -2), keepdim=True)).double()).abs().pow(2).mean((0, 1))
    f = torch.sqrt(torch.fft.fftfreq(h, dtype=torch.float64)[:, None] ** 2
                   + torch.fft.rfftfreq(w, dtype=torch.float64)[None, :] ** 2)
    m = (f > 0.02) & (f < 0.3)
    a = torch.stack([torch.ones(int(m.sum()), dtype=torch.float64), f[m].log()], 1)
    return float(torch.linalg.lstsq(a, spec[m].log()[:, None]).solution[1, 0])


def test_spectral_tilt_changes_the_power_slope_by_twice_its_exponent():
    x = fractal(128, _g(1), batch=2, beta=2.5)
    base = _power_slope(x)
    for a in (-0.5, 0.3, 0.8):
        y = spectral_tilt(x, a)
        assert y.shape == x.shape and float(y.min()) == 0.0 and float(y.max()) == 1.0
        assert _power_slope(y) - base == pytest.approx(2 * a, abs=0.02)
    # exponent 0 keeps a texture that already spans [0, 1] (only the min-max rescaling acts)
    z = stripes(SIZE, _g(2), period=7.0, angle=0.3)
    z = (z - z.amin((-1, -2), keepdim=True)) / (z.amax((-1, -2), keepdim=True) - z.amin((-1, -2), keepdim=True))
    assert torch.allclose(spectral_tilt(z, 0.0), z, atol=1e-6)
    # a constant image stays constant (no division by its zero span)
    assert torch.equal(spectral_tilt(torch.full((1, 1, 8, 8), 0.3), 0.5), torch.full((1, 1, 8, 8), 0.5))
    for bad in (float("nan"), float("inf"), True, "0.5"):
        with pytest.raises(InputError):
            spectral_tilt(x, bad)
    for f_ref in (0.0, -0.1, 0.6):
        with pytest.raises(InputError):
            spectral_tilt(x, 0.5, reference_frequency=f_ref)
    with pytest.raises(InputError):
        spectral_tilt(x[0], 0.5)


def test_random_texture_tilt_is_drawn_recorded_and_off_by_default():
    plain, info = random_texture(_g(3), SIZE, family="dead_leaves")
    assert "spectral_tilt" not in info
    # off: the same draws as before the option existed (nothing more is drawn from the generator)
    g1, g2 = _g(4), _g(4)
    random_texture(g1, SIZE, family="voronoi")
    random_texture(g2, SIZE, family="voronoi", spectral_tilt_max=0.0)
    assert torch.equal(torch.rand(3, generator=g1), torch.rand(3, generator=g2))
    tilted, tinfo = random_texture(_g(3), SIZE, family="dead_leaves", spectral_tilt_max=0.7)
    assert -0.7 <= tinfo["spectral_tilt"] <= 0.7
    assert {k: v for k, v in tinfo.items() if k != "spectral_tilt"} == info  # the same family draw
    lo, hi = info["albedo"] * (1 - info["contrast"]), info["albedo"]
    assert float(tilted.min()) >= lo - 1e-6 and float(tilted.max()) <= hi + 1e-6
    assert not torch.allclose(tilted, plain)
    assert "spectral_tilt" not in random_texture(_g(3), SIZE, family="flat", spectral_tilt_max=0.7)[1]
    for bad in (-0.1, float("nan"), True):
        with pytest.raises(InputError):
            random_texture(_g(3), SIZE, spectral_tilt_max=bad)


def test_register_and_errors():
    fam = register_texture("test_const", lambda shape, g, batch=1, level=0.5: torch.full((batch, 1, *shape), level),
                           lambda g, hw: {"level": 0.25})
    try:
        tex, p = random_texture(_g(0), (8, 8), family="test_const")
        assert p["level"] == 0.25 and fam.name == "test_const"
    finally:
        TEXTURE_FAMILIES.pop("test_const")
    with pytest.raises(InputError):
        stripes(16, _g(0), period=1.0)
    with pytest.raises(InputError):
        fractal((0, 4), _g(0))
    with pytest.raises(InputError):
        voronoi(16, _g(0), mode="hexagons")
