"""Focus-breathing registration before the estimator (tdfd.registration, tdfd.breathing helpers)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from tdfd import Camera
from tdfd.breathing import (breathing_scales, crop_offset, magnify, registration_magnifications,
                            window_shifts)
from tdfd.camera_file import CameraFile, resolve_camera_file
from tdfd.errors import CameraError, InputError, ModelError, NonFiniteError, RangeError, ShapeError
from tdfd.model import DFDModel
from tdfd.registration import BreathingRegistration, magnify_about_centre, register_breathing
from tdfd.textures import random_texture

pytestmark = pytest.mark.usefixtures("one_torch_thread")

REF = Camera.preset("reference")


def _texture(seed: int, h: int = 96, w: int = 128, blur_px: float = 0.0) -> torch.Tensor:
    tex, _ = random_texture(torch.Generator().manual_seed(seed), (h, w), family="fractal", contrast=(0.8, 1.0))
    tex = tex.double()
    if blur_px:  # a lens never passes the Nyquist frequency at full contrast
        r = torch.arange(-8, 9, dtype=torch.float64)
        k = torch.exp(-r**2 / (2 * blur_px**2))
        k = k / k.sum()
        tex = torch.nn.functional.conv2d(torch.nn.functional.pad(tex, (8, 8, 8, 8), mode="reflect"),
                                         (k[:, None] * k[None, :])[None, None])
    return tex


def test_magnify_moves_whole_pixels_about_the_centre():
    """Output pixel p is input pixel round(c + (p - c) / s) per axis: no interpolation, so every
    output value is an input value (the sensor noise stays white)."""
    x = np.random.default_rng(0).random((70, 101))  # odd and even sides
    for s in (1.004, 0.996, 1.03):
        got = magnify_about_centre(torch.from_numpy(x), s).numpy()
        iy = np.clip(np.round(34.5 + (np.arange(70) - 34.5) / s), 0, 69).astype(int)
        ix = np.clip(np.round(50.0 + (np.arange(101) - 50.0) / s), 0, 100).astype(int)
        assert np.array_equal(got, x[iy[:, None], ix[None, :]])


def test_registration_undoes_a_known_magnification():
    """Frames magnified by 1 + m P about the centre (numpy reference, Lanczos) are brought to
    their common scale: near the sides, where breathing moves the frames apart by about 2 px,
    what is left (whole-pixel rounding, below half a pixel per frame) is far less."""
    ideal = _texture(1, 256, 384, blur_px=1.0)
    s1, s2 = breathing_scales(0.01, REF.lens_powers_dpt)  # 1 % between the frames: 1.9 px at the sides
    f1 = torch.from_numpy(magnify(ideal[0, 0].numpy(), s1))[None, None]
    f2 = torch.from_numpy(magnify(ideal[0, 0].numpy(), s2))[None, None]
    r1, r2 = register_breathing(f1, f2, (s1, s2))
    common = torch.from_numpy(magnify(ideal[0, 0].numpy(), math.sqrt(s1 * s2)))[None, None]
    sides = (..., slice(10, -10), torch.cat([torch.arange(10, 60), torch.arange(324, 374)]))
    before = (f1 - f2)[sides].abs().mean()
    assert (r1 - r2)[sides].abs().mean() < 0.5 * before
    assert (r1 - common)[sides].abs().mean() < 0.5 * (f1 - common)[sides].abs().mean()
    assert (r2 - common)[sides].abs().mean() < 0.5 * (f2 - common)[sides].abs().mean()


def test_zero_breathing_is_exactly_the_identity_and_adds_nothing():
    x = _texture(2).float()
    y = x.flip(-1)
    reg = BreathingRegistration(0.0, REF.lens_powers_dpt)
    a, b = reg(x, y)
    assert a is x and b is y and not reg.enabled
    assert magnify_about_centre(x, 1.0) is x
    same_power = BreathingRegistration(0.01, (2.0, 2.0))  # equal powers: equal scales
    assert not same_power.enabled and same_power(x, y)[0] is x
    model = DFDModel(REF, tile=32, stride=32, hidden=8, blocks=1)
    assert model.magnification_per_dpt == 0.0 and not model.registration.enabled
    assert list(model.registration.parameters()) == [] and list(model.registration.buffers()) == []


def test_gradcheck_float64():
    x = torch.rand(1, 1, 20, 23, dtype=torch.float64, generator=torch.Generator().manual_seed(3), requires_grad=True)
    y = torch.rand(1, 1, 20, 23, dtype=torch.float64, generator=torch.Generator().manual_seed(4), requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: register_breathing(a, b, (1.0, 1.02)), (x, y), fast_mode=True)


def test_scales_magnifications_and_window_shifts():
    s1, s2 = breathing_scales(0.004, (1.0, 3.5))
    assert (s1, s2) == pytest.approx((1.004, 1.014))
    k1, k2 = registration_magnifications((s1, s2))
    assert k1 * s1 == pytest.approx(math.sqrt(s1 * s2)) and k2 * s2 == pytest.approx(math.sqrt(s1 * s2))
    assert k1 * k2 == pytest.approx(1.0)
    # a crop centred on the optical centre needs no translation; one 200 px off by (1 - 1/k)
    assert window_shifts(0.0, (k1, k2)) == (0.0, 0.0)
    t1, t2 = window_shifts(200.0, (k1, k2))
    assert t1 == pytest.approx(-200 * (1 - 1 / k1)) and t2 == pytest.approx(-200 * (1 - 1 / k2)) and t1 * t2 < 0


def test_crop_offset_moves_the_window_by_whole_pixels():
    img = np.arange(80 * 90, dtype=np.float64).reshape(80, 90)
    assert np.array_equal(crop_offset(img, (20, 52, 30, 70), (2, -3)), img[22:54, 27:67])
    assert np.array_equal(crop_offset(img, (20, 52, 30, 70)), img[20:52, 30:70])
    edge = crop_offset(img, (0, 10, 0, 10), (-2, 0))  # beyond the border: the border pixel
    assert np.array_equal(edge[:3], np.repeat(img[0:1, 0:10], 3, 0)) and np.array_equal(edge[3:], img[1:8, 0:10])
    with pytest.raises(ShapeError):
        crop_offset(img, (20, 100, 30, 70))
    with pytest.raises(InputError):
        crop_offset(img, (20, 52, 30, 70), (0.5, 0))


@pytest.mark.parametrize("bad, error", [(math.nan, NonFiniteError), (math.inf, NonFiniteError), (0.2, RangeError),
                                        (-0.1, RangeError), ("x", NonFiniteError)])
def test_bad_magnification_is_a_typed_error(bad, error):
    with pytest.raises(error, match="magnification_per_dpt"):
        BreathingRegistration(bad, REF.lens_powers_dpt)
    with pytest.raises(error):
        DFDModel(REF, tile=32, stride=32, hidden=8, blocks=1, magnification_per_dpt=bad)
    model = DFDModel(REF, tile=32, stride=32, hidden=8, blocks=1)
    with pytest.raises(error):
        model.set_breathing(bad)
    with pytest.raises((NonFiniteError, RangeError)):
        magnify_about_centre(torch.zeros(1, 1, 16, 16), bad if isinstance(bad, float) else math.nan)


def test_bad_scales_and_shapes():
    with pytest.raises(RangeError):
        breathing_scales(0.09, (-20.0, 0.0))  # 1 + m P below 0.5
    with pytest.raises(NonFiniteError):
        breathing_scales(0.001, (math.nan, 1.0))
    with pytest.raises(ShapeError):
        register_breathing(torch.zeros(1, 2, 16, 16), torch.zeros(1, 2, 16, 16), (1.0, 1.01))
    with pytest.raises(ShapeError):
        magnify_about_centre(torch.zeros(16), 1.01)


def test_model_registers_before_the_analytic_stage_and_keeps_its_fingerprint(tmp_path):
    """The model with breathing sees the pair as the registered pair; the weights, the
    features' fingerprint and the state dict do not change; save/load keeps ``m``."""
    torch.manual_seed(0)
    model = DFDModel(REF, tile=32, stride=32, hidden=8, blocks=1).eval()
    x = _texture(5, 96, 96).float()
    i1, i2 = x, x.roll(1, -1)
    breathing = DFDModel(REF, tile=32, stride=32, hidden=8, blocks=1, magnification_per_dpt=0.04).eval()
    breathing.load_state_dict(model.state_dict(), strict=True)
    r1, r2 = register_breathing(i1, i2, breathing.registration.scales)
    with torch.no_grad():
        for got, want in zip(breathing(i1, i2), model(r1, r2)):
            assert torch.equal(got, want)
        assert not torch.equal(breathing(i1, i2)[2], model(i1, i2)[2])
    assert breathing.analytic_fingerprint() == model.analytic_fingerprint()
    assert breathing.config()["magnification_per_dpt"] == 0.04
    breathing.save(tmp_path / "m")
    back = DFDModel.load(tmp_path / "m")
    assert back.magnification_per_dpt == 0.04 and back.analytic_matches is True
    assert model.set_breathing(0.04).registration.scales == breathing.registration.scales
    cfg = json.loads((tmp_path / "m.json").read_text())
    cfg["magnification_per_dpt"] = math.nan
    with pytest.raises(ModelError, match="magnification_per_dpt"):
        DFDModel.from_config(cfg)


def test_camera_file_resolution(tmp_path):
    path = CameraFile(REF, magnification_per_dpt=0.004).write(tmp_path / "cam.json")
    cf = resolve_camera_file(path)
    assert cf.camera == REF and cf.magnification_per_dpt == 0.004
    assert resolve_camera_file("reference").magnification_per_dpt == 0.0
    (tmp_path / "bad.json").write_text(json.dumps({**REF.to_dict(), "magnification_per_dpt": 0.5}))
    with pytest.raises(CameraError, match="bad.json: magnification_per_dpt 0.5 is implausible"):
        resolve_camera_file(tmp_path / "bad.json")
