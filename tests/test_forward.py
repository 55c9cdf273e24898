"""The forward model (tdfd.forward): each stage does what its parameters say, the stages
compose, and generated samples are a pure function of their seed."""

import math

import pytest
import torch

from tdfd import Camera
from tdfd.errors import InputError, ShapeError
from tdfd.forward import Defocus, DFDForward, IdealSensor, PlanePairs, defocus_pair, frame_gain, misregister
from tdfd.optics import defocus_uniform, psf_second_moment, sigma_map
from tdfd.sensor import SensorModel

CAM = Camera.preset("reference")


@pytest.fixture(autouse=True)
def _one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_defocus_pair_blurs_a_point_by_eq_4_and_eq_6():
    n, d = 61, 0.3
    x = torch.zeros(1, 1, n, n, dtype=torch.float64)
    x[..., n // 2, n // 2] = 1.0
    pair = defocus_pair(CAM, x, torch.full_like(x, d))
    for f, power in enumerate(CAM.lens_powers_dpt):
        sigma = float(sigma_map(CAM, torch.tensor([[[[d]]]], dtype=torch.float64), power))
        assert float(pair[0, f].sum()) == pytest.approx(1.0, abs=1e-9)
        assert math.sqrt(float(psf_second_moment(pair[0, f]))) == pytest.approx(math.sqrt(sigma ** 2 + 1 / 12), rel=0.01)
    # eq. 6: the two frames' blurs differ by the camera's constant
    s1 = float(sigma_map(CAM, torch.tensor([[[[d]]]], dtype=torch.float64), CAM.lens_powers_dpt[0]))
    ref2 = defocus_uniform(x, torch.tensor([s1 - CAM.sigma_difference_px], dtype=torch.float64))
    # (the pair's kernels share the larger frame's size: frame 2 keeps a little more tail)
    assert torch.allclose(pair[:, 1:], ref2, atol=1e-6)


def test_modes_agree_on_planes_and_psf_shapes_differ():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 1, 48, 48, generator=g)
    depth = torch.full_like(x, 0.6)
    a = Defocus(CAM, mode="occlusion")(x, depth)
    assert torch.allclose(a, Defocus(CAM, mode="gather")(x, depth), atol=1e-6)
    assert not torch.allclose(a, Defocus(CAM, psf="pillbox")(x, depth), atol=1e-3)
    with pytest.raises(InputError):
        Defocus(CAM, mode="fast")
    with pytest.raises(ShapeError):
        defocus_pair(CAM, x[:, :, :10], depth)
    with pytest.raises(InputError):
        defocus_pair(CAM, x, -depth)


def test_misregistration_and_gain_stages():
    h = w = 64
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    blob = torch.exp(-((yy - 40) ** 2 + (xx - 22) ** 2) / 18.0)
    frames = torch.stack([blob, blob])[None]
    out = misregister(frames, 0.0, 0.4, -0.3)

    def centroid(img):
        return float((img * yy).sum() / img.sum()), float((img * xx).sum() / img.sum())

    (y1, x1), (y2, x2) = centroid(out[0, 0]), centroid(out[0, 1])
    assert y2 - y1 == pytest.approx(0.4, abs=1e-3) and x2 - x1 == pytest.approx(-0.3, abs=1e-3)
    assert torch.equal(misregister(frames, 0.0, 0.0, 0.0), frames)
    g = frame_gain(frames - 0.1, 1.02)
    assert float(g.min()) == 0.0
    assert torch.allclose(g[0, 1], g[0, 0] * 1.02)
    with pytest.raises(ShapeError):
        misregister(frames[:, :1], 0.01, 0.0, 0.0)


def test_composition_equals_the_stages_by_hand():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 1, 40, 56, generator=g) * 0.8
    depth = torch.full_like(x, 0.45)
    depth[..., 30:] = 0.8
    sensor = SensorModel(full_well_e=8000.0, read_noise_e=4.0, bits=10, black_level_dn=8.0)
    fwd = DFDForward(Defocus(CAM, psf=6.0), sensor)
    got = fwd(x, depth, breathing=0.004, shift_x_px=0.2, frame_gain=0.99, generator=torch.Generator().manual_seed(7))
    hand = frame_gain(misregister(defocus_pair(CAM, x, depth, 6.0), 0.004, 0.0, 0.2), 0.99)
    assert torch.equal(got, sensor(hand, generator=torch.Generator().manual_seed(7)))
    assert torch.equal(DFDForward(Defocus(CAM), IdealSensor(2.0, 0.5))(x, depth), defocus_pair(CAM, x, depth).clamp(0, 1))


def test_plane_pairs_are_deterministic_per_seed_and_return_their_parameters():
    gen = PlanePairs(CAM)
    a, pa = gen.sample(2, 64, 80, seed=3)
    b, pb = gen.sample(2, 64, 80, seed=3)
    c, _ = gen.sample(2, 64, 80, seed=4)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a.shape == (2, 2, 64, 80) and a.dtype == torch.float32 and float(a.min()) >= 0 and float(a.max()) <= 1
    assert pa["depth_m"] == pb["depth_m"] and len(pa["depth_m"][0]) == 2 and len(pa["textures"]) == 2
    near, far = CAM.depth_range_m
    assert all(near <= d <= far for row in pa["depth_m"] for d in row)
    # the depth map holds the drawn planes, split at the drawn column
    cut = pa["split_columns"][0][0]
    assert float(pa["depth"][0, 0, 0, cut - 1]) == pytest.approx(pa["depth_m"][0][0], rel=1e-6)
    assert float(pa["depth"][0, 0, 0, cut]) == pytest.approx(pa["depth_m"][0][1], rel=1e-6)
