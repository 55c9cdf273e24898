"""The post-hoc calibration of the predicted error scale (issue 19): the map, its fit, the
model's JSON round trip, the ONNX export and the training stage that fits it."""

from __future__ import annotations

import json
import math

import numpy as np
import onnxruntime as ort
import pytest
import torch
from safetensors.torch import load_file

from export import export_model, realistic_pairs, verify_onnx
from export.testing import make_test_model
from tdfd import Camera
from tdfd.errors import InputError, ModelError
from tdfd.model import DFDModel
from tdfd.model.scale_calibration import (ScaleCalibration, calibrate_log_scale, piecewise_linear,
                                          tile_border_distance, validate_knots)
from tdfd.model.scale_calibration_fit import fit_scale_calibration, fit_tile_calibration, laplace_mixture_median
from tests.onnx_parity import assert_parity
from training import calibrate_scale

KNOTS = ([-6.0, -4.5, -3.0, -1.0], [-5.6, -4.4, -3.1, -1.0])  # factors 1.49, 1.11, 0.90, 1.00
#: every part: the scale knots above, a depth part over 0.4 .. 3 1/m and an edge part for 0, 1, 2 tiles
FULL = {"log_b": KNOTS[0], "log_b_calibrated": KNOTS[1], "inverse_depth_per_m": [0.4, 1.5, 3.0],
        "depth_log_shift": [0.3, -0.2, 0.1], "border_log_shift": [0.25, 0.1, -0.05]}


def _laplace(scale: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    u = torch.rand(scale.shape, generator=g, dtype=torch.float64) - 0.5
    return scale * -u.sign() * torch.log1p(-(2 * u.abs()).clamp(max=1 - 1e-12))  # rand's 0 would give inf


def test_map_is_interpolation_of_the_shift_with_the_end_shifts_held():
    x, y = (torch.tensor(k, dtype=torch.float64) for k in KNOTS)
    lb = torch.linspace(-9.0, 2.0, 301, dtype=torch.float64)
    want = lb.numpy() + np.interp(lb.numpy(), x.numpy(), (y - x).numpy())  # np.interp holds the end values
    got = calibrate_log_scale(lb, x, y)
    assert np.allclose(got.numpy(), want, atol=1e-12)
    assert float(got[0] - lb[0]) == pytest.approx(0.4) and float(got[-1] - lb[-1]) == pytest.approx(0.0)
    assert bool((got[1:] >= got[:-1]).all())  # keeps the confidence's order


def test_piecewise_linear_is_interpolation_with_the_ends_held():
    kx, ky = torch.tensor([0.4, 1.5, 3.0], dtype=torch.float64), torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    x = torch.linspace(0.0, 4.0, 201, dtype=torch.float64)
    assert np.allclose(piecewise_linear(x, kx, ky).numpy(), np.interp(x.numpy(), kx.numpy(), ky.numpy()), atol=1e-12)


def test_tile_border_distance_golden():
    want = torch.tensor([[0, 0, 0, 0, 0, 0],
                         [0, 1, 1, 1, 1, 0],
                         [0, 1, 2, 2, 1, 0],
                         [0, 1, 1, 1, 1, 0],
                         [0, 0, 0, 0, 0, 0]], dtype=torch.float32)
    got = tile_border_distance(torch.zeros(3, 2, 5, 6))
    assert got.shape == (1, 1, 5, 6) and torch.equal(got[0, 0], want)
    assert torch.equal(tile_border_distance(torch.zeros(1, 1, 1, 4)), torch.zeros(1, 1, 1, 4))
    with pytest.raises(InputError, match=r"\(B, C, h, w\)"):
        tile_border_distance(torch.zeros(5, 6))


def test_full_map_is_the_sum_of_its_parts():
    """``log b + s(log b) + g(q) + h(n)``, each part interpolated independently here with np.interp."""
    cal = ScaleCalibration(**FULL)
    g = torch.Generator().manual_seed(1)
    lb = torch.empty(2, 1, 5, 6).uniform_(-8.0, 0.0, generator=g)
    q = torch.empty(2, 1, 5, 6).uniform_(0.2, 3.5, generator=g)
    n = tile_border_distance(lb).expand_as(lb).numpy()
    x, y = np.array(KNOTS[0]), np.array(KNOTS[1])
    want = (lb.numpy() + np.interp(lb.numpy(), x, y - x)
            + np.interp(q.numpy(), FULL["inverse_depth_per_m"], FULL["depth_log_shift"])
            + np.interp(n, [0, 1, 2], FULL["border_log_shift"]))
    assert np.allclose(cal(lb, q).numpy(), want, atol=1e-5)
    with pytest.raises(InputError, match="inverse depth"):
        cal(lb)
    with pytest.raises(InputError, match="inverse depth"):
        cal(lb, q[:, :, :4])
    # the edge part alone needs no depth; the identity is untouched
    edge = ScaleCalibration(border_log_shift=FULL["border_log_shift"])
    assert np.allclose(edge(lb).numpy(), lb.numpy() + np.interp(n, [0, 1, 2], FULL["border_log_shift"]), atol=1e-6)
    assert torch.equal(ScaleCalibration()(lb, q), lb)


def test_full_map_gradcheck_float64():
    cal = ScaleCalibration(**FULL).double()
    lb = torch.linspace(-7.0, -0.5, 12, dtype=torch.float64).view(1, 1, 3, 4).requires_grad_()
    q = torch.linspace(0.3, 3.2, 12, dtype=torch.float64).view(1, 1, 3, 4).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: cal(a, b), (lb, q))


def test_map_gradcheck_float64():
    x, y = (torch.tensor(k, dtype=torch.float64) for k in KNOTS)
    lb = torch.tensor([-7.0, -5.3, -4.0, -2.2, -0.5], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: calibrate_log_scale(v, x, y), (lb,))


@pytest.mark.parametrize("x, y, match", [
    ([-5.0], [-5.0], "at least 2"),
    ([-5.0, -4.0, -3.0], [-5.0, -4.0], "as many"),
    ([-5.0, -5.0], [-5.0, -4.0], "strictly increasing"),
    ([-5.0, -4.0], [-4.0, -4.5], "non-decreasing"),
    ([-5.0, math.nan], [-5.0, -4.0], "finite"),
    ([-5.0, "a"], [-5.0, -4.0], "numbers"),
])
def test_bad_knots_are_named(x, y, match):
    with pytest.raises(InputError, match=match):
        validate_knots(x, y)


@pytest.mark.parametrize("cfg, match", [
    ({**FULL, "inverse_depth_per_m": [0.4, 0.4, 3.0]}, "strictly increasing"),
    ({**FULL, "inverse_depth_per_m": [-0.4, 1.5, 3.0]}, "positive"),
    ({**FULL, "depth_log_shift": [0.3, -0.2]}, "as many"),
    ({**FULL, "depth_log_shift": [0.3, math.inf, 0.1]}, "finite"),
    ({k: v for k, v in FULL.items() if k != "depth_log_shift"}, "both inverse_depth_per_m"),
    ({**FULL, "border_log_shift": [0.1]}, "at least 2"),
    ({**FULL, "border_log_shift": ["x", 0.1]}, "numbers"),
    ({**FULL, "edge": [0.1, 0.2]}, "keys among"),
    ({}, "non-empty"),
])
def test_bad_depth_or_edge_parts_are_named(cfg, match):
    with pytest.raises(InputError, match=match):
        ScaleCalibration.from_config(cfg)


def test_full_config_round_trip_and_an_older_description_loads():
    cal = ScaleCalibration.from_config(json.loads(json.dumps(ScaleCalibration(**FULL).to_config())))
    assert set(cal.to_config()) == set(FULL)
    for key, values in FULL.items():
        assert cal.to_config()[key] == pytest.approx(values, abs=1e-7), key
    old = ScaleCalibration.from_config({"log_b": KNOTS[0], "log_b_calibrated": KNOTS[1]})  # before the depth and edge parts
    assert set(old.to_config()) == {"log_b", "log_b_calibrated"}
    lb = torch.linspace(-8, 1, 30).view(1, 1, 5, 6)
    assert torch.allclose(old(lb), calibrate_log_scale(lb, *(torch.tensor(k) for k in KNOTS)))


def test_config_round_trip_and_identity():
    cal = ScaleCalibration(*KNOTS)
    again = ScaleCalibration.from_config(json.loads(json.dumps(cal.to_config())))
    lb = torch.linspace(-8, 1, 50)
    assert torch.allclose(again(lb), cal(lb))
    assert ScaleCalibration.from_config(None).to_config() is None
    assert torch.equal(ScaleCalibration()(lb), lb)
    with pytest.raises(InputError, match="log_b_calibrated"):
        ScaleCalibration.from_config({"log_b": [0.0, 1.0]})
    with pytest.raises(InputError, match="both"):
        ScaleCalibration([0.0, 1.0], None)


def test_fit_recovers_a_scale_dependent_miscalibration():
    """Errors Laplace with scale f(b) b, f from 1.5 at small b to 0.8 at large b: the fitted
    map's knots carry f, and through it every decile's median matches within 10 %."""
    g = torch.Generator().manual_seed(3)
    b = torch.exp(torch.empty(60000, dtype=torch.float64).uniform_(math.log(0.003), math.log(0.3), generator=g))
    factor = 1.5 - 0.7 * (b.log() - math.log(0.003)) / math.log(100.0)
    e = _laplace(factor * b, g)
    kb, kc = fit_scale_calibration(b, e, bins=20, smooth=3)
    want = 1.5 - 0.7 * (kb - math.log(0.003)) / math.log(100.0)
    assert bool((((kc - kb).exp() / want) - 1).abs()[2:-2].max() < 0.08)  # ends: the moving average's edge
    calibrated = calibrate_log_scale(b.log(), kb, kc).exp()
    order = torch.argsort(calibrated)
    for part in torch.tensor_split(order, 10):
        ratio = float(e[part].abs().median()) / laplace_mixture_median(calibrated[part])
        assert abs(ratio - 1) < 0.1


def test_tile_fit_recovers_depth_and_edge_dependent_miscalibration():
    """Errors Laplace with scale ``b f(b) g(q) h(n)``: the backfitted parts carry the shapes of
    ``g`` and ``h`` (up to the constant the parts can trade), and the calibrated scale matches
    the observed median within 10 % in every band of ``b``, of ``q`` and at every distance."""
    g = torch.Generator().manual_seed(7)
    count = 120000
    b = torch.exp(torch.empty(count, dtype=torch.float64).uniform_(math.log(0.003), math.log(0.3), generator=g))
    q = torch.empty(count, dtype=torch.float64).uniform_(1.0, 3.0, generator=g)
    n = torch.randint(0, 8, (count,), generator=g).double()
    f_b = 1.3 - 0.4 * (b.log() - math.log(0.003)) / math.log(100.0)
    f_q = 1.4 - 0.3 * (q - 1.0)  # far tiles (small q) err more: 1.4 at q = 1, 0.8 at q = 3
    f_n = torch.tensor([1.5, 1.2, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0], dtype=torch.float64)[n.long()]
    e = _laplace(b * f_b * f_q * f_n, g)
    cfg = fit_tile_calibration(b, e, q, n, bins=20, smooth=3, depth_bins=10, border_levels=4)
    assert set(cfg) == {"log_b", "log_b_calibrated", "inverse_depth_per_m", "depth_log_shift", "border_log_shift"}
    h = torch.tensor(cfg["border_log_shift"]).exp()
    assert float(h[0] / h[3]) == pytest.approx(1.5, rel=0.08) and float(h[1] / h[3]) == pytest.approx(1.2, rel=0.08)
    kx, ky = torch.tensor(cfg["inverse_depth_per_m"]), torch.tensor(cfg["depth_log_shift"])
    truth = (1.4 - 0.3 * (kx - 1.0)).log()
    inner = slice(1, -1)  # the moving average's ends
    assert bool(((ky - truth)[inner] - (ky - truth)[inner].mean()).abs().max() < 0.08)
    kb, kc = torch.tensor(cfg["log_b"]), torch.tensor(cfg["log_b_calibrated"])
    calibrated = torch.exp(calibrate_log_scale(b.log(), kb, kc) + piecewise_linear(q, kx, ky)
                           + h.log().double()[n.clamp(max=3).long()])
    for key in (b, q):
        for part in torch.tensor_split(torch.argsort(key), 8):
            assert abs(float(e[part].abs().median()) / laplace_mixture_median(calibrated[part]) - 1) < 0.1
    for level in range(8):
        part = n == level
        assert abs(float(e[part].abs().median()) / laplace_mixture_median(calibrated[part]) - 1) < 0.1
    plain = fit_tile_calibration(b, e, bins=20)  # neither part: the scale part alone, as fit_scale_calibration
    kb, kc = fit_scale_calibration(b, e, bins=20)
    assert plain == {"log_b": kb.tolist(), "log_b_calibrated": kc.tolist()}


def test_tile_fit_refuses_bad_input():
    b = torch.linspace(0.01, 0.1, 200, dtype=torch.float64)
    e = torch.linspace(-0.05, 0.05, 200, dtype=torch.float64)
    with pytest.raises(InputError, match="inverse_depth"):
        fit_tile_calibration(b, e, -torch.ones(200), bins=4)
    with pytest.raises(InputError, match="inverse_depth"):
        fit_tile_calibration(b, e, torch.ones(100), bins=4)
    with pytest.raises(InputError, match="whole numbers"):
        fit_tile_calibration(b, e, border=torch.full((200,), 0.5), bins=4)
    with pytest.raises(InputError, match="2 tiles 2 tiles from the edge"):
        fit_tile_calibration(b, e, border=torch.arange(200) % 2, bins=4, border_levels=3)
    with pytest.raises(InputError, match="depth bins"):
        fit_tile_calibration(b, e, torch.ones(200), bins=4, depth_bins=1)
    with pytest.raises(InputError, match="equal median inverse depth"):
        fit_tile_calibration(b, e, torch.ones(200), bins=4, depth_bins=4)
    with pytest.raises(InputError, match="rounds"):
        fit_tile_calibration(b, e, bins=4, rounds=0)


def test_min_factor_one_only_widens_the_scale():
    """With ``min_factor = 1`` a band whose errors are smaller than predicted
    keeps the CNN's scale; a band whose errors are larger is widened as without the bound."""
    g = torch.Generator().manual_seed(4)
    b = torch.exp(torch.empty(40000, dtype=torch.float64).uniform_(math.log(0.003), math.log(0.3), generator=g))
    factor = torch.where(b < 0.03, torch.full_like(b, 1.4), torch.full_like(b, 0.7))
    e = _laplace(factor * b, g)
    kb, kc = fit_scale_calibration(b, e, bins=10, smooth=1, min_factor=1.0)
    f = (kc - kb).exp()
    assert bool((f >= 1 - 1e-12).all())
    assert bool(((f[:3] - 1.4).abs() < 0.12).all()) and bool(((f[-3:] - 1.0).abs() < 1e-9).all())
    kb_free, kc_free = fit_scale_calibration(b, e, bins=10, smooth=1)  # the default: no bound
    assert bool((((kc_free - kb_free).exp()[-3:] - 0.7).abs() < 0.07).all())
    with pytest.raises(InputError, match="min_factor"):
        fit_scale_calibration(b, e, bins=10, min_factor=0.0)


def test_fit_refuses_bad_input():
    b, e = torch.full((100,), 0.01), torch.zeros(100)
    with pytest.raises(InputError, match="equal median"):
        fit_scale_calibration(b, e, bins=10)
    with pytest.raises(InputError, match="as many"):
        fit_scale_calibration(b, e[:50])
    with pytest.raises(InputError, match="positive"):
        fit_scale_calibration(torch.cat([b[:99], torch.tensor([-1.0])]), e, bins=2)
    with pytest.raises(InputError, match="odd"):
        fit_scale_calibration(torch.linspace(0.01, 1, 100), e, bins=4, smooth=2)
    with pytest.raises(InputError, match="tiles per bin"):
        fit_scale_calibration(torch.linspace(0.01, 1, 10), e[:10], bins=6)


def _pair(model: DFDModel, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    return realistic_pairs(model.camera, 2, 160, 192, seed=seed)


def test_model_applies_the_calibration_to_the_confidence_and_saves_it(tmp_path):
    model = make_test_model(0).eval()
    i1, i2 = _pair(model)
    with torch.no_grad():
        plain = model.analyse(i1, i2)
        model.scale_calibration = ScaleCalibration(*KNOTS)
        cal = model.analyse(i1, i2)
    want = calibrate_log_scale(plain.log_scale, *(torch.tensor(k) for k in KNOTS))
    assert torch.allclose(cal.log_scale, want, atol=1e-6)
    b = cal.log_scale.exp() / model.confidence_scale
    assert torch.allclose(cal.confidence, 1 / (1 + b * b), atol=1e-6)
    assert not torch.allclose(cal.confidence, plain.confidence, atol=1e-3)  # the knots move these tiles
    assert torch.equal(cal.depth, plain.depth)  # the depth is untouched
    weights, meta = model.save(tmp_path / "m")
    assert json.loads(meta.read_text())["scale_calibration"]["log_b"] == pytest.approx(KNOTS[0])
    loaded = DFDModel.load(tmp_path / "m").eval()
    with torch.no_grad():
        again = loaded.analyse(i1, i2)
    assert torch.allclose(again.confidence, cal.confidence, atol=1e-6)
    # the weights file does not hold the knots: an uncalibrated save has the same tensors
    model.scale_calibration = ScaleCalibration()
    w2, _ = model.save(tmp_path / "plain")
    a, c = load_file(str(weights)), load_file(str(w2))
    assert a.keys() == c.keys() and all(torch.equal(a[k], c[k]) for k in a)


def test_model_applies_the_depth_and_edge_parts_to_its_own_grid(tmp_path):
    model = make_test_model(0).eval()
    i1, i2 = _pair(model)
    with torch.no_grad():
        plain = model.analyse(i1, i2)
        model.scale_calibration = ScaleCalibration(**FULL)
        cal = model.analyse(i1, i2)
        want = ScaleCalibration(**FULL)(plain.log_scale, plain.inverse_depth)
    assert torch.allclose(cal.log_scale, want, atol=1e-6)
    n = tile_border_distance(plain.log_scale)
    assert float(n.max()) >= 1  # the grid has inner tiles, so the edge part varies over it
    assert torch.equal(cal.depth, plain.depth)
    model.save(tmp_path / "m")
    assert DFDModel.read_description(tmp_path / "m")["scale_calibration"].keys() == FULL.keys()
    with torch.no_grad():
        again = DFDModel.load(tmp_path / "m").eval().analyse(i1, i2)
    assert torch.allclose(again.confidence, cal.confidence, atol=1e-6)


def test_bad_calibration_in_a_model_description_is_a_model_error(tmp_path):
    model = make_test_model(0)
    _, meta = model.save(tmp_path / "m")
    cfg = json.loads(meta.read_text())
    cfg["scale_calibration"] = {"log_b": [-3.0, -4.0], "log_b_calibrated": [-3.0, -2.0]}
    meta.write_text(json.dumps(cfg))
    with pytest.raises(ModelError, match="strictly increasing"):
        DFDModel.load(tmp_path / "m")


def test_onnx_export_carries_the_calibration(tmp_path):
    """All three parts in the graph, on frame sizes whose grids differ (the edge part from the grid's shape)."""
    model = make_test_model(0)
    model.scale_calibration = ScaleCalibration(**FULL)
    path = tmp_path / "cal.onnx"
    export_model(model, path)
    report = verify_onnx(path, model, sizes=[(64, 64), (160, 192)], batches=[1, 2])
    assert_parity(report, cases=4)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    i1, i2 = _pair(model, seed=5)
    _, conf, _ = sess.run(None, {"image_f1": i1.numpy(), "image_f2": i2.numpy()})
    model.scale_calibration = ScaleCalibration()
    with torch.no_grad():
        _, conf_plain, _ = model.eval()(i1, i2)
    assert not np.allclose(conf, conf_plain.numpy(), atol=1e-3)  # the graph holds the map, not the identity


def test_training_stage_fits_and_writes_the_calibration(tmp_path):
    """``python -m training.calibrate_scale`` on a small model: the knots land in the JSON,
    the weights file is unchanged, the earlier ``extra`` is kept and the fit is recorded."""
    model = DFDModel(Camera.preset("reference"), tile=64, stride=32, hidden=8, blocks=1)
    model.save(tmp_path / "m", extra={"training": {"steps": 1}})
    before = (tmp_path / "m.safetensors").read_bytes()
    assert calibrate_scale.main(["--model", str(tmp_path / "m"), "--planes", "8", "--scenes", "1", "--bins", "4",
                                 "--smooth", "1", "--threads", "1", "--depth-bins", "3", "--border-levels", "2"]) == 0
    meta = json.loads((tmp_path / "m.json").read_text())
    cal = meta["scale_calibration"]
    assert len(cal["log_b"]) == 4 and cal["log_b_calibrated"] == sorted(cal["log_b_calibrated"])
    assert meta["extra"]["training"] == {"steps": 1}
    fit = meta["extra"]["scale_calibration_fit"]
    assert fit["planes"] == 8 and fit["scenes_per_layout"] == 1 and fit["plane_seed"] == calibrate_scale.PLANE_SEED
    assert fit["tiles"] > fit["plane_tiles"] > 0  # planes and structure scenes both counted
    assert (tmp_path / "m.safetensors").read_bytes() == before
    assert set(DFDModel.load(tmp_path / "m").scale_calibration.to_config()) == {
        "log_b", "log_b_calibrated", "inverse_depth_per_m", "depth_log_shift", "border_log_shift"}
    assert len(cal["border_log_shift"]) == 2 and fit["border_levels"] == 2 and fit["depth_bins"] == 3
    # the figure of the parts
    assert calibrate_scale.main(["--model", str(tmp_path / "m"), "--out", str(tmp_path / "p"), "--planes", "8",
                                 "--scenes", "1", "--bins", "4", "--smooth", "1", "--threads", "1", "--depth-bins", "3",
                                 "--border-levels", "2", "--plot", str(tmp_path / "fig" / "cal.png")]) == 0
    assert (tmp_path / "fig" / "cal.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(InputError, match="no scale calibration"):
        calibrate_scale.plot_scale_calibration(ScaleCalibration(), tmp_path / "none.png")
    # without the depth and edge parts: the scale part alone
    assert calibrate_scale.main(["--model", str(tmp_path / "m"), "--out", str(tmp_path / "s"), "--planes", "8",
                                 "--scenes", "1", "--bins", "4", "--smooth", "1", "--threads", "1", "--depth-bins", "0",
                                 "--border-levels", "0"]) == 0
    assert set(json.loads((tmp_path / "s.json").read_text())["scale_calibration"]) == {"log_b", "log_b_calibrated"}


@pytest.mark.parametrize("flag", ["--depth-bins", "--border-levels"])
def test_training_stage_refuses_one_band(tmp_path, flag, capsys):
    with pytest.raises(SystemExit):
        calibrate_scale.main(["--model", str(tmp_path / "m"), flag, "1"])
    assert "0 (without that part) or >= 2" in capsys.readouterr().err


def test_tile_fit_normalises_the_parts_without_changing_the_map():
    """``h`` is 0 for the innermost level, ``g``'s median over the tiles is 0: the constant the
    parts can trade sits in ``s``; the map at every tile is what the unnormalised parts give."""
    g = torch.Generator().manual_seed(11)
    count = 40000
    b = torch.exp(torch.empty(count, dtype=torch.float64).uniform_(math.log(0.003), math.log(0.3), generator=g))
    q = torch.empty(count, dtype=torch.float64).uniform_(1.0, 3.0, generator=g)
    n = torch.randint(0, 4, (count,), generator=g).double()
    e = _laplace(b * 1.3 * (1.2 - 0.1 * q) * (1.0 + 0.3 * (n == 0)), g)
    cfg = fit_tile_calibration(b, e, q, n, bins=10, depth_bins=8, border_levels=3, rounds=3)
    assert cfg["border_log_shift"][-1] == 0.0 and cfg["border_log_shift"][0] == pytest.approx(math.log(1.3), abs=0.08)
    g_q = piecewise_linear(q, torch.tensor(cfg["inverse_depth_per_m"], dtype=torch.float64),
                           torch.tensor(cfg["depth_log_shift"], dtype=torch.float64))
    assert abs(float(g_q.median())) < 1e-6
    # the overall level (the constant) sits in s: about 1.3 times the scale at the middle of the range
    lb = calibrate_log_scale(b.log(), torch.tensor(cfg["log_b"]), torch.tensor(cfg["log_b_calibrated"])) + g_q
    assert float((lb - b.log()).median().exp()) == pytest.approx(1.3 * 1.0, rel=0.1)
