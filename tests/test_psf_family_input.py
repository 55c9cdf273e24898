"""The lens's PSF family as an input of the refinement CNN: the code, training's per-sample
draw, the model, the export that bakes it in and the runtime that overrides it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tdfd.camera import Camera
from tdfd.camera_file import PSF_FAMILY_VALUES, CameraFile
from tdfd.contract import PSF_FAMILY_KEY
from tdfd.errors import InputError, ModelError, ShapeError
from tdfd.model import DFDModel, append_family_maps, family_code, num_features, training_codes
from tdfd.model.psf_family_code import FAMILY_CODES
from tdfd.runtime import DepthRuntime
from tdfd.runtime_psf_family import FAMILIES, read_psf_family


def _model(seed: int = 0, **kw) -> DFDModel:
    """A small model with the family input and a random (non-zero) CNN."""
    torch.manual_seed(seed)
    m = DFDModel(Camera.preset("reference"), tile=64, stride=32, psf_family_input=True, hidden=16, blocks=1, **kw)
    with torch.no_grad():
        for p in m.refine.parameters():
            p.normal_(0.0, 0.05)
    return m.eval()


def _pair(h: int = 160, w: int = 192) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    x1 = torch.rand(1, 1, h, w, generator=g) * 0.8 + 0.1
    return x1, x1.roll(2, -1) * 0.9 + 0.05


# ------------------------------------------------------------------ the code
def test_codes_name_the_camera_file_families():
    assert FAMILY_CODES == PSF_FAMILY_VALUES == FAMILIES


def test_family_code_values_and_errors():
    assert family_code("gaussian").tolist() == [1.0, 0.0]
    assert family_code("pillbox").tolist() == [0.0, 1.0]
    assert family_code(None).tolist() == [0.0, 0.0]
    with pytest.raises(InputError, match="psf_family"):
        family_code("disk")


def test_append_family_maps_broadcasts_per_batch_and_per_sample():
    f = torch.randn(3, 4, 2, 5)
    out = append_family_maps(f, family_code("pillbox"))
    assert out.shape == (3, 6, 2, 5) and torch.equal(out[:, :4], f)
    assert bool((out[:, 4] == 0).all()) and bool((out[:, 5] == 1).all())
    per = torch.tensor([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
    out = append_family_maps(f, per)
    assert torch.equal(out[:, 4:, 1, 3], per)
    with pytest.raises(ShapeError, match="codes"):
        append_family_maps(f, torch.zeros(2, 2))
    with pytest.raises(ShapeError, match="codes"):
        append_family_maps(f, torch.zeros(3))


# ------------------------------------------------------------------ training's draw
def _params(n: int, shape: str) -> list[dict]:
    return [{"psf_shape": shape, "sample_seed": 1000 + 7919 * i} for i in range(n)]


def test_training_codes_tell_known_families_a_share_of_the_time():
    codes = training_codes(_params(400, "pillbox"), 0.5)
    told = codes[:, 1] == 1
    assert bool((codes[:, 0] == 0).all())
    assert 160 <= int(told.sum()) <= 240  # binomial(400, 0.5): 5 sigma
    assert torch.equal(codes, training_codes(_params(400, "pillbox"), 0.5))  # a function of the sample
    assert torch.equal(training_codes(_params(5, "gaussian"), 1.0), torch.tensor([[1.0, 0.0]] * 5))
    assert not training_codes(_params(5, "gaussian"), 0.0).any()
    assert not training_codes(_params(5, "beta"), 1.0).any()  # power-exponential: never told


def test_training_codes_errors():
    with pytest.raises(InputError, match="told_share"):
        training_codes(_params(2, "gaussian"), 1.5)
    with pytest.raises(InputError, match="sample_seed"):
        training_codes([{"psf_shape": "pillbox"}], 0.5)
    assert not training_codes([None, {"psf_shape": "beta"}], 1.0).any()


# ------------------------------------------------------------------ the model
def test_model_features_end_with_the_code_and_fresh_model_is_analytic():
    m = DFDModel(Camera.preset("reference"), tile=64, stride=32, psf_family_input=True, hidden=8, blocks=1,
                 psf_family="pillbox").eval()
    x1, x2 = _pair()
    feats, _ = m.features(x1, x2)
    assert feats.shape[1] == num_features(m.analytic.num_rings) + 2
    assert bool((feats[:, -2] == 0).all()) and bool((feats[:, -1] == 1).all())
    depth, _, depth_a = m(x1, x2)
    assert torch.equal(depth, depth_a)  # zero head: the code changes nothing yet
    feats, _ = m.features(x1, x2, torch.tensor([[1.0, 0.0]]))
    assert bool((feats[:, -2] == 1).all())


def test_the_family_changes_a_trained_cnn_and_only_through_the_code():
    m = _model()
    x1, x2 = _pair()
    with torch.no_grad():
        d = {f: m.set_psf_family(f)(x1, x2) for f in ("gaussian", "pillbox", None)}
    assert not torch.allclose(d["gaussian"][0], d["pillbox"][0])
    assert torch.equal(d["gaussian"][2], d["pillbox"][2])  # the analytic depth does not see it
    with torch.no_grad():
        r = m.set_psf_family(None).analyse(x1, x2, torch.tensor([[0.0, 1.0]]))
    assert torch.equal(r.depth, d["pillbox"][0])


def test_model_without_input_refuses_a_family():
    m = DFDModel(Camera.preset("reference"), hidden=8, blocks=1)
    with pytest.raises(InputError, match="without the PSF family input"):
        m.set_psf_family("gaussian")
    x1, x2 = _pair()
    with pytest.raises(InputError, match="psf_family_codes"):
        m.features(x1, x2, torch.zeros(1, 2))
    with pytest.raises(ModelError, match="invalid model description"):
        DFDModel.from_config({**m.config(), "psf_family": "pillbox"})


def test_save_load_keeps_the_input_and_the_family(tmp_path):
    m = _model(psf_family="pillbox")
    m.save(tmp_path / "m")
    back = DFDModel.load(tmp_path / "m")
    assert back.psf_family_input and back.psf_family == "pillbox"
    assert back.analytic_matches is True  # the fingerprint is the analytic stage's, code aside
    x1, x2 = _pair()
    with torch.no_grad():
        assert torch.equal(back(x1, x2)[0], m(x1, x2)[0])
    assert "psf_family_code" not in back.state_dict()  # told, not learnt: the JSON holds it


def test_featurizer_tells_each_sample_its_own_family():
    from training.config import load_config
    from training.data import Featurizer

    cfg = load_config(None, ["model.psf_family_input=true", "model.psf_family_told_share=1.0", "model.hidden=8",
                             "model.blocks=1"])
    fz = Featurizer(cfg.model)
    x1, x2 = _pair(128, 128)
    params = [{"psf_shape": "pillbox", "sample_seed": 5}, {"psf_shape": "beta", "sample_seed": 6}]
    out = fz({"image_f1": x1.expand(2, -1, -1, -1), "image_f2": x2.expand(2, -1, -1, -1),
              "tile_depth": torch.full((2, 1, 3, 3), 0.5), "params": params})
    assert out["features"][:, -2:, 0, 0].tolist() == [[0.0, 1.0], [0.0, 0.0]]


def test_config_rejects_a_told_share_outside_unit_interval():
    from training.config import ConfigError, load_config

    with pytest.raises(ConfigError, match="psf_family_told_share"):
        load_config(None, ["model.psf_family_told_share=1.5"])


# ------------------------------------------------------------------ export and runtime
@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    from export.onnx_export import export_model

    m = _model(psf_family="gaussian")
    path = tmp_path_factory.mktemp("family") / "family.onnx"
    export_model(m, path)
    return path, m


def test_export_records_the_baked_family(exported):
    path, _ = exported
    rt = DepthRuntime(path)
    assert rt.metadata[PSF_FAMILY_KEY] == {"input": True, "family": "gaussian", "initializer": "psf_family_code"}
    assert rt.psf_family == "gaussian" and rt.psf_family_info.takes_input


@pytest.mark.parametrize("family", ["exported", "pillbox", "unknown", None])
def test_runtime_told_a_family_matches_torch(exported, family):
    path, m = exported
    x1, x2 = _pair()
    rt = DepthRuntime(path, threads=1, psf_family=family)
    want = {"exported": "gaussian", "unknown": None}.get(family, family)
    assert rt.psf_family == want
    depth, conf, _ = rt.run(x1.numpy(), x2.numpy())
    with torch.no_grad():
        t_depth, t_conf, _ = m.set_psf_family(want)(x1, x2)
    np.testing.assert_allclose(depth, t_depth.numpy(), rtol=1e-3)  # export.verify's tolerances
    np.testing.assert_allclose(conf, t_conf.numpy(), atol=1e-3)
    other = {"gaussian": "pillbox"}.get(want, "gaussian")
    with torch.no_grad():
        assert not np.allclose(depth, m.set_psf_family(other)(x1, x2)[0].numpy(), rtol=1e-3)


def test_runtime_switches_family_in_place(exported):
    path, _ = exported
    x1, x2 = _pair()
    rt = DepthRuntime(path, threads=1)
    g = rt.run(x1.numpy(), x2.numpy())[0]
    p = rt.set_psf_family("pillbox").run(x1.numpy(), x2.numpy())[0]
    assert rt.psf_family == "pillbox" and not np.allclose(g, p)
    np.testing.assert_array_equal(rt.set_psf_family("gaussian").run(x1.numpy(), x2.numpy())[0], g)
    with pytest.raises(InputError, match="psf_family"):
        rt.set_psf_family("disk")


def test_runtime_refuses_a_family_for_a_model_without_input(tmp_path_factory):
    from export.testing import session_onnx_model

    path, _ = session_onnx_model(tmp_path_factory)
    rt = DepthRuntime(path)
    assert not rt.psf_family_info.takes_input and rt.psf_family is None
    with pytest.raises(ModelError, match="without the PSF family input"):
        DepthRuntime(path, psf_family="pillbox")


@pytest.mark.parametrize("bad", [{"input": True, "family": "disk", "initializer": "c"},
                                 {"input": False, "family": None, "initializer": "c"},
                                 {"input": True, "family": None, "initializer": ""}, {"family": None}, "gaussian"])
def test_invalid_family_metadata_is_refused(bad):
    with pytest.raises(ModelError, match=PSF_FAMILY_KEY):
        read_psf_family({PSF_FAMILY_KEY: bad}, "x.onnx")


def test_export_cli_bakes_the_camera_files_family(tmp_path):
    from export.__main__ import main

    _model().save(tmp_path / "m")
    cam = CameraFile(Camera.preset("reference"), psf_family="pillbox").write(tmp_path / "cam.json")
    assert main(["--weights", str(tmp_path / "m.safetensors"), "--camera", str(cam), "--out",
                 str(tmp_path / "m.onnx"), "--sizes", "64x64", "--batches", "1"]) == 0
    meta = DepthRuntime(tmp_path / "m.onnx").metadata[PSF_FAMILY_KEY]
    assert meta["family"] == "pillbox"
    assert json.loads((tmp_path / "m.json").read_text())["psf_family"] is None  # the saved model is untouched


def test_autofocus_tells_an_estimator_that_takes_the_family(exported):
    from tdfd.autofocus.estimators import OnnxEstimator
    from tdfd.autofocus.psf_family_option import tell_estimator

    path, _ = exported
    est = OnnxEstimator(path)
    tell_estimator(est, None)  # unknown: the exported family stays
    assert est.psf_family == "gaussian"
    tell_estimator(est, "pillbox")
    assert est.takes_psf_family and est.psf_family == "pillbox"


def test_evaluation_tells_only_gaussian_and_pillbox_samples():
    from data_synth import DefocusPairDataset
    from training.evaluate import collect

    m = _model()
    ds = DefocusPairDataset(seed=0, size=(128, 128), camera=m.camera)
    shapes = [ds[i]["params"]["psf_shape"] for i in range(6)]
    assert {"gaussian", "pillbox", "beta"} <= set(shapes)  # this stream's first six hold every kind
    unknown, told = collect(m, ds, 6, chunk=3), collect(m, ds, 6, chunk=3, tell_family=True)
    per = unknown["refined"].numel() // 6
    for i, shape in enumerate(shapes):
        same = torch.equal(unknown["refined"][i * per:(i + 1) * per], told["refined"][i * per:(i + 1) * per])
        assert same == (shape == "beta"), (i, shape)
    assert torch.equal(unknown["analytic"], told["analytic"])
