"""Each ring's orientation moments (``tdfd.dfd.orientation``) and the model that gives them to
its CNN (``DFDModel(orientation_input=True)``): against ``torch.fft``, symmetries, gradients,
typed errors, save/load, the training config and the ONNX export."""

from __future__ import annotations

import math

import pytest
import torch

from tdfd.camera import Camera
from tdfd.dfd import FourierRatioDFD, TileSpectra, fft_tile_power
from tdfd.dfd.orientation import RingOrientation, orientation_weights
from tdfd.errors import InputError, ModelError, ShapeError
from tdfd.model import DFDModel, num_features
from tests.onnx_parity import assert_parity

RINGS = torch.arange(2, 14)


def _fft_moments(x: torch.Tensor, tile: int, stride: int, rings: torch.Tensor) -> torch.Tensor:
    """The moments from the full FFT plane, summed bin by bin: ``(B, 2R, h, w)``."""
    power = fft_tile_power(x, tile, stride)  # (B, h, w, T, T), rows = k_y
    f = torch.fft.fftfreq(tile, d=1.0 / tile).double()
    ky, kx = f[:, None], f[None, :]
    radius, theta = torch.round(torch.sqrt(kx ** 2 + ky ** 2)), torch.atan2(ky, kx)
    cos_m, sin_m = [], []
    for r in rings.tolist():
        member = (radius == r).double()
        total = (power * member).sum((-1, -2))
        cos_m.append((power * member * torch.cos(2 * theta)).sum((-1, -2)) / total)
        sin_m.append((power * member * torch.sin(2 * theta)).sum((-1, -2)) / total)
    return torch.stack(cos_m + sin_m, 1)


def _textured(h: int = 128, w: int = 160, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.arange(float(h)), torch.arange(float(w)), indexing="ij")
    grating = torch.cos(2 * math.pi * (5 * x + 3 * y) / 64) + 0.5 * torch.cos(2 * math.pi * (-2 * x + 7 * y) / 64)
    return (torch.rand(2, 1, h, w, generator=g, dtype=torch.float64) + grating.double()) * 0.2 + 0.5


@pytest.mark.parametrize("tile,stride", [(64, 32), (32, 16)])
def test_moments_equal_the_fft_planes_sums(tile, stride):
    spectra = TileSpectra(tile, stride)
    rings = torch.arange(2, spectra.max_bin + 1)
    got = RingOrientation(spectra, rings)(spectra.coefficients(_textured()))
    want = _fft_moments(_textured(), tile, stride, rings)
    assert got.shape == want.shape == (2, 2 * len(rings), *want.shape[2:])
    torch.testing.assert_close(got, want, rtol=0, atol=1e-10)


@pytest.mark.parametrize("angle_deg", [0.0, 30.0, 45.0, 90.0, 120.0])
def test_one_grating_gives_its_doubled_angle(angle_deg):
    """A grating of frequency 8 cycles per tile at angle theta: its ring's moments are
    (cos 2 theta, sin 2 theta), up to the window's leakage into neighbouring bins."""
    th = math.radians(angle_deg)
    y, x = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
    img = torch.cos(2 * math.pi * 8 * (math.cos(th) * x + math.sin(th) * y) / 64).double()[None, None]
    spectra = TileSpectra(64, 64)
    m = RingOrientation(spectra, RINGS)(spectra.coefficients(img)).squeeze()
    c, s = m[RINGS.tolist().index(8)], m[len(RINGS) + RINGS.tolist().index(8)]
    assert abs(float(c) - math.cos(2 * th)) < 0.05 and abs(float(s) - math.sin(2 * th)) < 0.05


def test_transposing_the_image_negates_c_and_keeps_s():
    x = _textured(128, 128)
    spectra = TileSpectra(64, 32)
    mod = RingOrientation(spectra, RINGS)
    a, b = mod(spectra.coefficients(x)), mod(spectra.coefficients(x.transpose(-1, -2)))
    r = len(RINGS)
    torch.testing.assert_close(b[:, :r], -a[:, :r].transpose(-1, -2), rtol=0, atol=1e-10)
    torch.testing.assert_close(b[:, r:], a[:, r:].transpose(-1, -2), rtol=0, atol=1e-10)


def test_given_totals_equal_computed_ones_and_are_checked():
    spectra = TileSpectra(64, 32)
    mod = RingOrientation(spectra, RINGS)
    a = spectra.coefficients(_textured())
    totals = torch.nn.functional.conv2d(a * a, spectra.ring_weights(RINGS)[:, :, None, None])
    torch.testing.assert_close(mod(a, totals), mod(a), rtol=0, atol=1e-12)
    with pytest.raises(ShapeError, match="ring totals"):
        mod(a, totals[:, :-1])
    with pytest.raises(ShapeError, match="coefficients"):
        mod(a[:, :-1])


def test_weights_vanish_on_the_axes_for_sin_and_are_odd_for_cos():
    spectra = TileSpectra(64, 32)
    cos_w, sin_w = orientation_weights(spectra, RINGS)
    k1 = spectra.max_bin + 1
    sin_grid = sin_w.reshape(len(RINGS), k1, k1)  # (ring, kx, ky)
    assert float(sin_grid[:, 0, :].abs().max()) == 0.0 and float(sin_grid[:, :, 0].abs().max()) == 0.0
    cos_grid = cos_w.reshape(len(RINGS), 2, k1, 2, k1)[:, 0, :, 0]  # (ring, kx, ky)
    torch.testing.assert_close(cos_grid, -cos_grid.transpose(1, 2), rtol=0, atol=1e-15)


def test_gradcheck_float64():
    spectra = TileSpectra(16, 8)
    mod = RingOrientation(spectra, torch.arange(1, spectra.max_bin + 1))
    g = torch.Generator().manual_seed(1)
    x = (torch.rand(1, 1, 24, 24, generator=g, dtype=torch.float64) + 0.5).requires_grad_()
    assert torch.autograd.gradcheck(lambda t: mod(spectra.coefficients(t)), (x,))


def test_estimator_measures_both_frames_moments_with_its_rings():
    est = FourierRatioDFD(Camera.preset("reference"))
    x = _textured().float()
    f1, f2 = x[:1], x[1:]
    meas, moments = est.measure_oriented(f1, f2)
    for got, want in zip(meas, est.measure(f1, f2)):
        assert torch.equal(got, want)
    r = est.num_rings
    assert moments.shape[1] == 4 * r
    spectra = est.spectra
    own = RingOrientation(spectra, torch.arange(est.min_bin, spectra.max_bin + 1))
    torch.testing.assert_close(moments[:, :2 * r], own(spectra.coefficients(f1)), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(moments[:, 2 * r:], own(spectra.coefficients(f2)), rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------ the model
def _model(orientation_input: bool = True, seed: int = 0, **kw) -> DFDModel:
    """A small model with a random (non-zero) CNN."""
    torch.manual_seed(seed)
    m = DFDModel(Camera.preset("reference"), orientation_input=orientation_input, hidden=16, blocks=2,
                 dilation_base=2, **kw)
    with torch.no_grad():
        for p in m.refine.parameters():
            p.normal_(0.0, 0.05)
    return m.eval()


def _pair(h: int = 160, w: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
    x = _textured(h, w).float()
    return x[:1], x[1:]


def test_model_features_carry_the_moments_before_the_family_code():
    m = DFDModel(Camera.preset("reference"), orientation_input=True, psf_family_input=True, psf_family="pillbox",
                 hidden=8, blocks=1).eval()
    x1, x2 = _pair()
    feats, _ = m.features(x1, x2)
    n, r = num_features(m.analytic.num_rings), m.analytic.num_rings
    assert feats.shape[1] == n + 4 * r + 2 == m.refine.in_channels
    torch.testing.assert_close(feats[:, n:n + 4 * r], m.analytic.measure_oriented(x1, x2)[1])
    assert bool((feats[:, -1] == 1).all())  # the family code stays last
    depth, _, depth_a = m(x1, x2)
    assert torch.equal(depth, depth_a)  # a fresh model is the analytic one


def test_the_moments_change_a_trained_cnn_and_the_plain_model_has_none():
    m, plain = _model(True), _model(False)
    assert plain.refine.in_channels == m.refine.in_channels - 4 * m.analytic.num_rings
    x1, x2 = _pair()
    feats, r = m.features(x1, x2)
    turned = feats.clone()
    n = num_features(m.analytic.num_rings)
    turned[:, n:] = -turned[:, n:]  # other moments, the same ring sums
    with torch.no_grad():
        q = m.head(feats, r.inverse_depth, r.rel_error)[0]
        q_turned = m.head(turned, r.inverse_depth, r.rel_error)[0]
    assert float((q - q_turned).abs().max()) > 1e-4


@pytest.mark.parametrize("bad", [1, "yes", None])
def test_model_refuses_a_bad_orientation_input(bad):
    with pytest.raises(InputError, match="orientation_input"):
        DFDModel(Camera.preset("reference"), orientation_input=bad, hidden=8, blocks=1)


def test_save_load_keeps_the_input(tmp_path):
    m = _model(True)
    m.save(tmp_path / "m")
    back = DFDModel.load(tmp_path / "m")
    assert back.orientation_input is True and back.config()["orientation_input"] is True
    x1, x2 = _pair()
    with torch.no_grad():
        assert torch.equal(back(x1, x2)[0], m(x1, x2)[0])


def test_a_description_without_the_key_loads_without_the_moments():
    cfg = _model(False).config()
    del cfg["orientation_input"]
    assert DFDModel.from_config(cfg).orientation_input is False
    with pytest.raises(ModelError, match="invalid model description"):
        DFDModel.from_config({**cfg, "orientation_input": "no"})


def test_training_config_builds_the_model_with_the_moments():
    from training.config import ConfigError, load_config
    from training.data import Featurizer

    cfg = load_config(None, ["model.orientation_input=true", "model.hidden=8", "model.blocks=1"])
    fz = Featurizer(cfg.model)
    assert fz.model.orientation_input is True
    x1, x2 = _pair(128, 160)
    out = fz({"image_f1": x1, "image_f2": x2, "tile_depth": torch.full((1, 1, 3, 4), 0.5)})
    n = num_features(fz.model.analytic.num_rings, fz.model.contexts)
    torch.testing.assert_close(out["features"][:, n:], fz.model.analytic.measure_oriented(x1, x2)[1])
    with pytest.raises(ConfigError, match="orientation_input"):
        load_config(None, ["model.orientation_input=3"])


def test_reference_config_trains_with_the_moments():
    from training.config import load_config

    assert load_config("training/configs/reference.toml").model.orientation_input is True


# ------------------------------------------------------------------ export
def test_export_computes_the_moments_like_torch(tmp_path):
    from export import export_model, verify_onnx

    m = _model(True)
    path = tmp_path / "orientation.onnx"
    export_model(m, path)
    report = verify_onnx(path, m, sizes=[(64, 64), (97, 161), (192, 320)], batches=[1, 2])
    assert_parity(report, cases=6)
