"""Sensor model: Poisson-Gaussian statistics, black level, quantisation, saturation."""

import pytest
import torch

from tdfd.errors import InputError, ShapeError
from tdfd.sensor import SensorModel, poisson_gaussian, quantize, shot_noise, vignetting, white_level


def _g(seed=0):
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize("level,full_well,read,gain,bits", [
    (0.3, 10000.0, 3.0, 1.0, 12),
    (0.05, 2000.0, 8.0, 4.0, 12),
    (0.6, 30000.0, 2.0, 1.0, 10),
])
def test_flat_field_mean_and_variance_match_the_model(level, full_well, read, gain, bits):
    sensor = SensorModel(full_well_e=full_well, read_noise_e=read, bits=bits, black_level_dn=32, gain=gain,
                         exposure=1.0 / gain)
    x = torch.full((1, 1, 256, 256), level, dtype=torch.float64)
    y = sensor(x, generator=_g(1))
    n = y.numel()
    mean, var = float(y.mean()), float(y.var())
    em, ev = float(sensor.expected_mean(torch.tensor(level))), float(sensor.expected_variance(torch.tensor(level)))
    assert mean == pytest.approx(em, abs=4 * (ev / n) ** 0.5 + 1e-7)
    assert var == pytest.approx(ev, rel=4 * (2.0 / n) ** 0.5 + 0.02)


def test_exact_poisson_at_low_counts():
    lam = torch.full((200_000,), 2.5, dtype=torch.float64)
    e = shot_noise(lam, _g(0))
    assert bool((e == e.round()).all())  # integer electron counts
    assert float(e.mean()) == pytest.approx(2.5, abs=0.02)
    assert float(e.var()) == pytest.approx(2.5, abs=0.05)
    # above the threshold the normal approximation has the same mean and variance
    e = poisson_gaussian(torch.full((200_000,), 400.0, dtype=torch.float64), 5.0, _g(1))
    assert float(e.mean()) == pytest.approx(400.0, abs=0.3)
    assert float(e.var()) == pytest.approx(425.0, rel=0.03)


def test_black_level_quantisation_levels_and_range():
    for bits in (8, 10, 12):
        sensor = SensorModel(bits=bits, black_level_dn=16, read_noise_e=2.0)
        x = torch.rand(1, 1, 64, 64, generator=_g(bits))
        y = sensor(x, generator=_g(0))
        white = white_level(bits)
        codes = y.double() * white
        assert torch.allclose(codes, codes.round(), atol=1e-3)
        assert float(y.min()) >= 0.0 and float(y.max()) <= 1.0
        assert len(torch.unique(codes.round())) <= white + 1
    dark = SensorModel(bits=10, black_level_dn=64, noise=False)(torch.zeros(1, 1, 4, 4))
    assert torch.all(dark == 64 / 1023)  # raw / white level, black level included


def test_saturation_clips_at_white_and_full_well():
    sensor = SensorModel(full_well_e=5000, bits=12, black_level_dn=0, read_noise_e=0.0)
    y = sensor(torch.full((1, 1, 32, 32), 3.0), generator=_g(0))
    assert torch.all(y == 1.0)
    # with gain 4 the ADC clips at a quarter of the well
    sensor = SensorModel(full_well_e=5000, bits=12, black_level_dn=0, gain=4.0, noise=False)
    y = sensor(torch.tensor([0.1, 0.2, 0.3]).reshape(1, 1, 1, 3))
    assert float(y[..., 0]) == pytest.approx(0.4, abs=1e-3) and float(y[..., 2]) == 1.0


def test_vignetting_and_per_sample_parameters():
    x = torch.ones(2, 1, 33, 33)
    v = vignetting(x, torch.tensor([0.0, 0.3]))
    assert torch.all(v[0] == 1.0)
    assert float(v[1, 0, 16, 16]) == pytest.approx(1.0) and float(v[1, 0, 0, 0]) == pytest.approx(0.7)
    sensor = SensorModel(full_well_e=torch.tensor([1000.0, 50000.0]), bits=12, black_level_dn=0)
    y = sensor(torch.full((2, 1, 128, 128), 0.5), generator=_g(0))
    assert float(y[0].std()) > 3 * float(y[1].std())  # the small well is noisier


def test_determinism_and_errors():
    sensor = SensorModel()
    x = torch.rand(1, 2, 32, 32, generator=_g(0))
    assert torch.equal(sensor(x, generator=_g(3)), sensor(x, generator=_g(3)))
    assert not torch.equal(sensor(x, generator=_g(3)), sensor(x, generator=_g(4)))
    with pytest.raises(InputError):
        SensorModel(bits=20)
    with pytest.raises(InputError):
        SensorModel(black_level_dn=5000, bits=12)
    with pytest.raises(InputError):
        SensorModel(vignetting=1.2)
    with pytest.raises(ShapeError):
        sensor(torch.rand(32, 32))
    with pytest.raises(ShapeError):
        SensorModel(gain=torch.ones(3))(torch.rand(2, 1, 4, 4))
    assert torch.equal(quantize(torch.tensor([-3.0, 2.4, 300.0]).reshape(1, 1, 1, 3), 8).flatten(),
                       torch.tensor([0.0, 2.0, 255.0]))


def test_one_noise_draw_saturates_before_read_noise():
    lam = torch.full((1, 1, 200, 200), 5000.0, dtype=torch.float64)
    e = poisson_gaussian(lam, 4.0, _g(2), full_well_e=4000.0)  # the well clips, then read noise adds
    assert float(e.mean()) == pytest.approx(4000.0, abs=0.1) and float(e.std()) == pytest.approx(4.0, rel=0.03)
    e = poisson_gaussian(torch.full((1, 1, 200, 200), 900.0, dtype=torch.float64), 4.0, _g(3), full_well_e=1e5)
    assert float(e.var()) == pytest.approx(916.0, rel=0.03)


def test_numpy_callers_get_the_same_frames():
    import numpy as np

    sensor = SensorModel(full_well_e=5000.0, read_noise_e=2.0, bits=10, black_level_dn=16)
    x = torch.rand(48, 64, generator=_g(5))
    got = sensor.apply_numpy(x.numpy(), seed=9)
    assert got.dtype == np.float32 and got.shape == (48, 64)
    assert np.array_equal(got, sensor(x[None, None], generator=_g(9))[0, 0].numpy())
    with pytest.raises(ShapeError):
        sensor.apply_numpy(np.zeros((2, 3, 4)), seed=0)
