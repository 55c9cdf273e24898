"""Image formation of the synthesiser: a point source blurs to the thin-lens blur circle,
energy is preserved, PSF variants keep their size, breathing and misregistration are what
the parameters say, and the fast renderer paths agree with the core renderer."""

import math

import pytest
import torch

from data_synth import PSFModel, render_frames, warp_pair
from data_synth.psf import batch_kernel_fn
from tdfd.textures import fractal
from tdfd import Camera
from tdfd.errors import InputError
from tdfd.optics import (camera_blur_radii_px, camera_sigmas, defocus_layered, defocus_layered_multi, defocus_uniform,
                         psf_second_moment, render_pair, sigma_map)

CAM = Camera.preset("reference")
N = 65


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _point(dtype=torch.float64):
    x = torch.zeros(1, 1, N, N, dtype=dtype)
    x[..., N // 2, N // 2] = 1.0
    return x


@pytest.mark.parametrize("shape", ["gaussian", "pillbox"])
@pytest.mark.parametrize("depth", [0.3, 0.45, 1.0])
def test_point_source_blur_matches_thin_lens_geometry(shape, depth):
    frames = render_frames(CAM, _point(), torch.full((1, 1, N, N), depth, dtype=torch.float64), PSFModel(shape))
    for f, power in enumerate(CAM.lens_powers_dpt):
        spot = frames[0, f]
        # geometric blur-circle radius r_b (paper eq. 3) in px, and sigma = mu r_b (eq. 4)
        r_px = abs(float(camera_blur_radii_px(CAM, depth, power)))
        sigma = abs(float(sigma_map(CAM, torch.tensor([[[[depth]]]], dtype=torch.float64), power)))
        assert sigma == pytest.approx(r_px / 2)  # the reference camera's mu = 1 / (2 pitch)
        assert float(spot.sum()) == pytest.approx(1.0, abs=1e-9)  # energy preserved
        assert float(spot.min()) >= -1e-12
        # second moment per axis: sigma^2 (+ 1/12 px^2 of pixel integration)
        assert float(psf_second_moment(spot)) ** 0.5 == pytest.approx(math.sqrt(sigma ** 2 + 1 / 12), rel=0.03)
        if shape == "pillbox" and r_px > 2:
            # a uniform disk of the blur-circle radius: its area gives the radius
            area = float((spot > 0.5 * spot.max()).sum())
            assert math.sqrt(area / math.pi) == pytest.approx(r_px, abs=0.5)
            yy, xx = torch.meshgrid(torch.arange(N) - N // 2, torch.arange(N) - N // 2, indexing="ij")
            inside = spot[(yy ** 2 + xx ** 2).double().sqrt() < r_px - 1]
            assert float(inside.std() / inside.mean()) < 1e-6  # flat top


def test_point_source_through_the_layered_and_core_renderers():
    # the same spot through the occluding layered path (depth map with a far step elsewhere)
    depth = torch.full((1, 1, N, N), 0.45, dtype=torch.float64)
    depth[..., :, :6] = 0.9
    occl = render_frames(CAM, _point(), depth, PSFModel("pillbox"), mode="occlusion", layer_spacing=0.05)
    s1, s2 = camera_sigmas(CAM, 0.45)
    for f, s in enumerate((s1, s2)):
        ref = defocus_uniform(_point(), s.reshape(1).double(), "pillbox")[0, 0]
        assert float(occl[0, f].sum()) == pytest.approx(1.0, abs=1e-6)
        assert torch.allclose(occl[0, f], ref, atol=2e-3)
    g1, g2 = render_pair(CAM, _point(), torch.full((1, 1, N, N), 0.45, dtype=torch.float64), "gaussian")
    mine = render_frames(CAM, _point(), torch.full((1, 1, N, N), 0.45, dtype=torch.float64), PSFModel("gaussian"))
    # one kernel-size rule and one Gaussian (tdfd.optics.psf): frame 1 is the same spot to
    # rounding; frame 2 differs only by eq. 6's constant offset against the per-pixel map
    assert torch.allclose(mine[0, 0], g1[0, 0], atol=1e-12) and torch.allclose(mine[0, 1], g2[0, 0], atol=1e-6)


@pytest.mark.parametrize("model", [
    PSFModel(5.0), PSFModel("pillbox", diffraction_sigma_px=0.5), PSFModel("gaussian", diffraction_sigma_px=0.6),
    PSFModel(3.0, astigmatism=0.15, astigmatism_angle=0.7, spherical=0.3),
    PSFModel("pillbox", astigmatism=0.1, spherical=-0.3),
])
def test_psf_variants_sum_to_one_keep_their_size_and_are_deltas_at_focus(model):
    s = torch.tensor([0.0, 1.5, -2.5, 4.0], dtype=torch.float64)
    k = model.kernels(s)
    assert torch.allclose(k.sum((-1, -2)), torch.ones(4, dtype=torch.float64), atol=1e-9)
    assert float(k.min()) >= 0
    var = psf_second_moment(k) + psf_second_moment(k.transpose(-1, -2))  # both axes
    expect = 2 * (s ** 2 * (1 + model.astigmatism ** 2) + 1 / 12 + model.diffraction_sigma_px ** 2)
    assert torch.allclose(var[1:], expect[1:], rtol=0.06)
    if model.diffraction_sigma_px == 0:
        c = k.shape[-1] // 2
        assert float(k[0, c, c]) == pytest.approx(1.0, abs=1e-6)
    # a float32 kernel at zero blur stays finite (large power-exponential beta)
    k32 = PSFModel(15.0).kernels(torch.tensor([0.0, 0.2]))
    assert bool(torch.isfinite(k32).all())


@pytest.mark.parametrize("shape", ["gaussian", "pillbox", 12.0])
def test_supersampled_kernels_keep_sum_and_size(shape):
    s = torch.tensor([0.0, 2.0, -3.0], dtype=torch.float64)
    model = PSFModel(shape, diffraction_sigma_px=0.4)
    fine = model.kernels(s, supersample=9)
    assert fine.shape == model.kernels(s).shape
    assert torch.allclose(fine.sum((-1, -2)), torch.ones(3, dtype=torch.float64), atol=1e-9)
    var = psf_second_moment(fine[1:]) + psf_second_moment(fine[1:].transpose(-1, -2))
    assert torch.allclose(var, 2 * (s[1:] ** 2 + 1 / 12 + 0.16), rtol=0.06)
    with pytest.raises(InputError, match="odd"):
        model.kernels(s, supersample=4)


def test_supersampled_kernels_vary_smoothly_with_the_shape():
    # kappa = 1 / beta -> 0 approaches the pillbox: the kernel's change per step of kappa
    # should shrink smoothly there. Pixel-centre samples of the hard-edged profile jump by
    # about the same amount at every step (pixels crossing the edge); 9x supersampled, not.
    s = torch.tensor([-2.73], dtype=torch.float64)
    kappas = (0.005, 0.01, 0.015, 0.02, 0.025, 0.03, 0.035)
    ks = [PSFModel(1 / k).kernels(s, size=15, supersample=9) for k in kappas]
    steps = [float((b - a).abs().sum()) for a, b in zip(ks, ks[1:])]
    assert all(b > a for a, b in zip(steps, steps[1:])) and steps[0] < 0.5 * steps[-1]


def test_astigmatism_swaps_axes_across_focus():
    m = PSFModel("gaussian", astigmatism=0.2, astigmatism_angle=0.0)
    k = m.kernels(torch.tensor([3.0, -3.0], dtype=torch.float64))
    vx, vy = psf_second_moment(k), psf_second_moment(k.transpose(-1, -2))
    assert float(vx[0]) > float(vy[0]) and float(vx[1]) < float(vy[1])


def _centroid(img):
    h, w = img.shape
    y = torch.arange(h, dtype=img.dtype)[:, None]
    x = torch.arange(w, dtype=img.dtype)[None, :]
    m = img.sum()
    return float((img * y).sum() / m), float((img * x).sum() / m)


def test_breathing_and_misregistration_of_the_second_frame():
    h = w = 96
    img = torch.zeros(1, 1, h, w, dtype=torch.float64)
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    for cy, cx in ((20.0, 20.0), (75.0, 70.0)):
        img[0, 0] += torch.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * 2.0 ** 2))
    pair = img.expand(1, 2, h, w).contiguous()
    assert torch.equal(warp_pair(pair, 0.0, 0.0, 0.0), pair)
    out = warp_pair(pair, 0.01, 0.3, -0.2)
    c = (h - 1) / 2
    for sl in (slice(0, 48), slice(48, 96)):
        y1, x1 = _centroid(out[0, 0, sl, sl])
        y2, x2 = _centroid(out[0, 1, sl, sl])
        y1, x1, y2, x2 = y1 + sl.start, x1 + sl.start, y2 + sl.start, x2 + sl.start
        # frame 2 = frame 1 magnified by 1.01 about the centre, then shifted by (0.3, -0.2)
        assert y2 == pytest.approx(c + (y1 - c) * 1.01 + 0.3, abs=1e-3)
        assert x2 == pytest.approx(c + (x1 - c) * 1.01 - 0.2, abs=1e-3)
    assert float(out.sum() / pair.sum()) == pytest.approx(1.0, abs=0.01)


def test_multi_frame_renderer_paths():
    x = fractal(48, torch.Generator().manual_seed(0), 2, beta=1.5).double()
    s = torch.linspace(-2.0, 1.5, 48, dtype=torch.float64).expand(2, 1, 48, 48).contiguous()
    s[1, :, :, 24:] = 2.5  # an occlusion edge in sample 1
    c = -CAM.sigma_difference_px
    both = defocus_layered_multi(x, s, torch.tensor([0.0, c], dtype=torch.float64), "pillbox")
    # frame 1 is exactly defocus_layered; frame 2 matches its own layered render closely
    assert torch.allclose(both[:, 0], defocus_layered(x, s, "pillbox"), atol=1e-12)
    assert float((both[:, 1] - defocus_layered(x, s + c, "pillbox")).abs().mean()) < 5e-3
    # gather agrees with the occluding render where the map is smooth (sample 0)
    gath = defocus_layered_multi(x, s, torch.tensor([0.0, c], dtype=torch.float64), "pillbox", occlusion=False)
    assert float((gath[0] - both[0]).abs().mean()) < 5e-3
    # exact planes equal the uniform blur; custom kernels are used
    flat = torch.full_like(s, 1.3)
    ex = defocus_layered_multi(x, flat, torch.tensor([0.0, c], dtype=torch.float64), "gaussian", exact_planes=True)
    assert torch.allclose(ex[:, 1], defocus_uniform(x, torch.full((2,), 1.3 + c, dtype=torch.float64)), atol=1e-12)
    fn = batch_kernel_fn([PSFModel("pillbox"), PSFModel("gaussian")])
    mixed = defocus_layered_multi(x, flat, torch.tensor([0.0, c], dtype=torch.float64), kernel_fn=fn, exact_planes=True)
    assert torch.allclose(mixed[0, 0], defocus_uniform(x[:1], torch.tensor([1.3], dtype=torch.float64), "pillbox")[0], atol=1e-12)
    assert torch.allclose(mixed[1, 0], ex[1, 0], atol=1e-12)
    # gradients reach the blur offsets (camera parameters) too
    off = torch.tensor([0.0, c], dtype=torch.float64, requires_grad=True)
    defocus_layered_multi(x, s, off, "gaussian").sum().backward()
    assert off.grad is not None and float(off.grad.abs()[1]) > 0
