"""The on-the-fly dataset: determinism per (seed, index), workers, batches, contents."""

import json

import pytest
import torch
from torch.utils.data import DataLoader, default_collate

from data_synth import PARAM_KEYS, DefocusPairDataset, SynthBatchGenerator, SynthConfig, sample_seed
from data_synth.params import inverse_depth_range
from tdfd import Camera
from tdfd.errors import InputError
from tdfd.grid import grid_shape, tile_true_depth
from tdfd.optics import camera_sigmas
from tdfd.textures import random_texture

SIZE = 64
KW = dict(size=SIZE, tile=32, stride=16)


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _same(a, b):
    for k in ("image_f1", "image_f2", "depth", "tile_depth"):
        if not torch.equal(a[k], b[k]):
            return False
    return a["params"] == b["params"]


def test_same_seed_same_bytes_different_seed_different_scene():
    a = DefocusPairDataset(seed=11, **KW)
    b = DefocusPairDataset(seed=11, **KW)
    c = DefocusPairDataset(seed=12, **KW)
    for i in (0, 5, 17):
        x, y, z = a[i], b[i], c[i]
        assert _same(x, y)
        assert x["image_f1"].numpy().tobytes() == y["image_f1"].numpy().tobytes()
        assert not torch.equal(x["image_f1"], z["image_f1"])
        assert not torch.equal(x["depth"], z["depth"]) or x["params"]["details"] != z["params"]["details"]
    # order of requests does not matter, indices give different scenes
    assert _same(a[3], b[3]) and not torch.equal(a[3]["image_f1"], a[4]["image_f1"])
    assert sample_seed(11, 3) != sample_seed(11, 4) and sample_seed(11, 3) != sample_seed(12, 3)


def test_dataloader_workers_give_the_same_samples():
    ds = DefocusPairDataset(seed=3, length=6, **KW)
    serial = list(DataLoader(ds, batch_size=None, num_workers=0))
    parallel = list(DataLoader(ds, batch_size=None, num_workers=2))
    assert len(serial) == len(parallel) == 6
    for s, p in zip(serial, parallel):
        assert _same(s, p)


def test_batch_path_equals_items_and_collates():
    ds = DefocusPairDataset(seed=5, **KW)
    batch = ds.batch([4, 1, 7])
    assert batch["image_f1"].shape == (3, 1, SIZE, SIZE)
    for j, i in enumerate((4, 1, 7)):
        item = ds[i]
        assert torch.equal(batch["image_f1"][j], item["image_f1"])
        assert torch.equal(batch["tile_depth"][j], item["tile_depth"])
        assert batch["params"][j] == item["params"]
    collated = default_collate([ds[0], ds[1]])  # params have fixed keys and plain values
    assert collated["image_f2"].shape == (2, 1, SIZE, SIZE)
    assert set(collated["params"]) == set(PARAM_KEYS)
    gen = SynthBatchGenerator(SIZE, seed=5, config=ds.config)
    assert torch.equal(gen.batch([4])["image_f2"][0], batch["image_f2"][0])


def test_sample_contents_shapes_ranges_and_ground_truth():
    cam = Camera.preset("reference")
    ds = DefocusPairDataset(seed=0, **KW)
    q_lo, q_hi = inverse_depth_range(cam, ds.config.depth_margin)
    h, w = grid_shape(SIZE, SIZE, 32, 16)
    layouts = set()
    for i in range(12):
        s = ds[i]
        p = s["params"]
        layouts.add(p["layout"])
        for k in ("image_f1", "image_f2"):
            assert s[k].shape == (1, SIZE, SIZE) and s[k].dtype == torch.float32
            assert bool(torch.isfinite(s[k]).all()) and float(s[k].min()) >= 0 and float(s[k].max()) <= 1
            codes = s[k].double() * (2 ** p["bits"] - 1)  # raw / white level: integer codes
            assert torch.allclose(codes, codes.round(), atol=1e-3)
        assert s["depth"].shape == (1, SIZE, SIZE)
        q = 1.0 / s["depth"]
        assert float(q.min()) >= q_lo * (1 - 1e-5) and float(q.max()) <= q_hi * (1 + 1e-5)
        assert s["tile_depth"].shape == (1, h, w)
        expect = tile_true_depth(s["depth"][None], 32, 16, ds.generator.window)[0]
        assert torch.allclose(s["tile_depth"], expect)
        assert set(p) == set(PARAM_KEYS) and p["index"] == i and p["seed"] == 0
        assert p["depth_min_m"] == pytest.approx(float(s["depth"].min()), rel=1e-5)
        assert abs(p["breathing"]) <= 0.01 and abs(p["shift_x_px"]) <= 0.5
    assert len(layouts) >= 3


def test_depth_is_uniform_in_inverse_depth_over_the_extended_range():
    cam = Camera.preset("reference")
    ds = DefocusPairDataset(seed=1, size=16, tile=16, stride=16, layouts=["plane"], noise=False, illumination_prob=0.0)
    q_lo, q_hi = inverse_depth_range(cam, 0.1)
    assert (1 / q_hi, 1 / q_lo) == pytest.approx((0.3 / 1.1, 1.1))
    q = torch.tensor([1.0 / float(ds[i]["depth"][0, 0, 0]) for i in range(150)])
    u = (q - q_lo) / (q_hi - q_lo)
    assert float(u.min()) >= 0 and float(u.max()) <= 1
    assert float(u.mean()) == pytest.approx(0.5, abs=0.08)  # uniform: mean 1/2, sd 1/sqrt(12 n)
    assert float((u < 0.25).float().mean()) == pytest.approx(0.25, abs=0.1)


def test_options_families_psf_shapes_noise_and_errors():
    ds = DefocusPairDataset(seed=2, families=["checkers"], psf_shapes=["pillbox"], noise=False,
                            illumination_prob=0.0, **KW)
    for i in range(4):
        p = ds[i]["params"]
        assert p["psf_shape"] == "pillbox" and p["illumination"] == "none" and not p["noise"]
        assert set(p["texture_families"].split(",")) == {"checkers"}
    lit = DefocusPairDataset(seed=2, illumination_prob=1.0, **KW)
    kinds = {lit[i]["params"]["illumination"] for i in range(8)}
    assert kinds <= {"coherent", "projector"} and kinds
    sharp = DefocusPairDataset(seed=2, return_sharp=True, **KW)[0]
    assert sharp["sharp"].shape == (1, SIZE, SIZE)
    assert DefocusPairDataset(size=(48, 80), tile=32, stride=16)[0]["image_f1"].shape == (1, 48, 80)
    with pytest.raises(InputError):
        DefocusPairDataset(families=["photos"], **KW)
    with pytest.raises(InputError):
        DefocusPairDataset(psf_shapes=["square"], **KW)
    with pytest.raises(InputError):
        DefocusPairDataset(size=16, tile=32, stride=16)
    with pytest.raises(InputError):
        SynthConfig(layouts={"cubes": 1.0})
    cfg = SynthConfig(breathing_max=0.005)
    assert SynthConfig.from_dict(cfg.to_dict()) == cfg


def test_frames_carry_the_defocus_cue():
    # noise-free fronto planes: the frame nearer to focus is the sharper one (paper eq. 4/6)
    cam = Camera.preset("reference")
    ds = DefocusPairDataset(seed=4, size=96, tile=32, stride=32, layouts=["plane"], noise=False,
                            illumination_prob=0.0, families=["fractal", "bandlimited", "dead_leaves"],
                            breathing_prob=0.0, shift_prob=0.0, frame_gain_jitter=0.0, aberration_prob=0.0)
    checked = 0
    for i in range(10):
        s = ds[i]
        s1, s2 = camera_sigmas(cam, float(s["depth"][0, 0, 0]))
        b1, b2 = abs(float(s1)), abs(float(s2))
        if abs(b1 - b2) < 0.5:
            continue
        e1 = float(torch.diff(s["image_f1"], dim=-1).pow(2).mean())
        e2 = float(torch.diff(s["image_f2"], dim=-1).pow(2).mean())
        if min(e1, e2) < 1e-9:
            continue
        assert (e1 > e2) == (b1 < b2)
        checked += 1
    assert checked >= 5


def test_same_bytes_whatever_the_number_of_torch_threads():
    # DataLoader workers run one thread, the main process two: at 256 x 256 torch's parallel
    # reductions would differ in the last bit, so the synthesiser avoids them
    ds = DefocusPairDataset(size=256, seed=21, illumination_prob=0.5)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        a = [ds[i] for i in range(6)]
        torch.set_num_threads(1)
        b = [ds[i] for i in range(6)]
    finally:
        torch.set_num_threads(before)
    for x, y in zip(a, b):
        assert _same(x, y)


def test_weighted_families_follow_their_weights_and_leave_the_uniform_mix_alone():
    # a weight of 0 is never drawn; the others in proportion (3 : 1 here, 600 draws: a share of 0.75 +- 0.018)
    cfg = SynthConfig(families={"stripes": 3.0, "checkers": 1.0, "dots": 0.0})
    g = torch.Generator().manual_seed(5)
    draws = [random_texture(g, 8, families=cfg.families)[1]["family"] for _ in range(600)]
    assert "dots" not in draws and set(draws) == {"stripes", "checkers"}
    assert abs(draws.count("stripes") / 600 - 0.75) < 0.06
    # the scenes carry the drawn families, and the weights survive the config's round trip
    ds = DefocusPairDataset(seed=3, families={"stripes": 1.0, "dots": 0.0}, layouts={"plane": 1.0},
                            illumination_prob=0.0, **KW)
    assert all(ds[i]["params"]["texture_families"] == "stripes" for i in range(3))
    assert SynthConfig.from_dict(cfg.to_dict()) == cfg
    # a list keeps the uniform draw (600 draws of two: a share of 0.5 +- 0.02), so its scenes are unchanged
    assert SynthConfig(families=["stripes", "checkers"]).families == ("stripes", "checkers")
    uniform = [random_texture(g, 8, families=("stripes", "checkers"))[1]["family"] for _ in range(600)]
    assert abs(uniform.count("stripes") / 600 - 0.5) < 0.06
    for bad in ({"stripes": -1.0}, {"stripes": float("nan")}, {"stripes": True}, {"stripes": 0.0},
                {"photos": 1.0}, {"stripes": "2"}):
        with pytest.raises(InputError):
            SynthConfig(families=bad)
        with pytest.raises(InputError):  # the texture library refuses the same mappings itself
            random_texture(g, 8, families=bad)


def test_spectral_tilt_option_tilts_every_textured_surface_and_defaults_off():
    # every surface but a flat one (its faint variation is no texture to tilt)
    assert SynthConfig().spectral_tilt == 0.0
    ds = DefocusPairDataset(seed=6, spectral_tilt=0.5, layouts={"layout": 1.0}, illumination_prob=0.0, **KW)
    plain = DefocusPairDataset(seed=6, layouts={"layout": 1.0}, illumination_prob=0.0, **KW)
    for i in range(3):
        tex = json.loads(ds[i]["params"]["details"])["textures"]
        assert tex and all(abs(t["spectral_tilt"]) <= 0.5 for t in tex if t["family"] != "flat")
        assert all("spectral_tilt" not in t for t in json.loads(plain[i]["params"]["details"])["textures"])
    assert SynthConfig.from_dict(SynthConfig(spectral_tilt=0.25).to_dict()).spectral_tilt == 0.25
    for bad in (-0.1, 2.5, float("nan"), True, "0.5"):
        with pytest.raises(InputError):
            SynthConfig(spectral_tilt=bad)
