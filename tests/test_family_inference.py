"""The image-wide PSF family inference: the pooled verdict, the code it completes, the model
option, its persistence, its ONNX export and the training that supervises it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tdfd.camera import Camera
from tdfd.errors import InputError, ShapeError
from tdfd.model import DFDModel
from tdfd.model.family_inference import FAMILY_CLASSES, FamilyInference, complete_family_code, family_classes
from tdfd.runtime import DepthRuntime
from training.losses import family_loss


def _model(seed: int = 0, **kw) -> DFDModel:
    """A small model with the family input, the inference and a random (non-zero) CNN."""
    torch.manual_seed(seed)
    m = DFDModel(Camera.preset("reference"), tile=64, stride=32, psf_family_input=True, family_inference=True,
                 hidden=16, blocks=1, **kw)
    with torch.no_grad():
        for p in m.refine.parameters():
            p.normal_(0.0, 0.05)
        for p in m.refine.family.parameters():  # a verdict that differs between frames
            p.normal_(0.0, 0.5)
    return m.eval()


def _pair(h: int = 160, w: int = 192, seed: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x1 = torch.rand(1, 1, h, w, generator=g) * 0.8 + 0.1
    return x1, x1.roll(2, -1) * 0.9 + 0.05


# ------------------------------------------------------------------ the layer
def test_verdict_is_a_weighted_mean_of_tile_logits():
    layer = FamilyInference(in_channels=3, hidden=4).double()
    x = torch.randn(2, 3, 4, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    code, logits = layer(x)
    out = layer.net(x)
    w = torch.sigmoid(out[:, 3:])
    want = (w * out[:, :3]).sum((2, 3)) / w.sum((2, 3))
    torch.testing.assert_close(logits, want)
    torch.testing.assert_close(code.flatten(1), torch.softmax(want, 1)[:, :2])


def test_verdict_is_per_image_and_the_same_for_a_tiled_frame():
    layer = FamilyInference(in_channels=3, hidden=4)
    x = torch.randn(2, 3, 4, 5, generator=torch.Generator().manual_seed(1))
    _, both = layer(x)
    _, first = layer(x[:1])
    torch.testing.assert_close(both[:1], first)  # never across the batch
    _, twice = layer(torch.cat([x[:1], x[:1]], -1))  # the same tiles twice: a mean, not a sum
    torch.testing.assert_close(twice, first, atol=1e-5, rtol=1e-5)


def test_a_tile_of_zero_weight_does_not_vote():
    layer = FamilyInference(in_channels=2, hidden=3)
    with torch.no_grad():  # the weight logit follows feature 0: a tile with feature 0 = -1e4 weighs 0
        layer.net[0].weight.zero_()
        layer.net[0].bias.zero_()
        layer.net[0].weight[0, 0, 0, 0] = 1.0
        layer.net[0].weight[1, 1, 0, 0] = 1.0
        layer.net[2].weight.zero_()
        layer.net[2].bias.zero_()
        layer.net[2].weight[3, 0, 0, 0] = 1.0  # weight logit = silu(feature 0) - 20
        layer.net[2].bias[3] = -20.0
        layer.net[2].weight[0, 1, 0, 0] = 1.0  # Gaussian logit = silu(feature 1)
    x = torch.zeros(1, 2, 1, 2)
    x[0, 0, 0, 0], x[0, 1, 0, 0] = 30.0, 2.0  # voting tile
    x[0, 0, 0, 1], x[0, 1, 0, 1] = -30.0, 50.0  # silenced tile with a loud opinion
    with torch.no_grad():
        _, logits = layer(x)
    assert abs(float(logits[0, 0]) - float(torch.nn.functional.silu(torch.tensor(2.0)))) < 1e-3


def test_gradcheck_float64():
    layer = FamilyInference(in_channels=3, hidden=4).double()
    x = torch.randn(2, 3, 2, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2), requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: layer(t)[1], (x,))


def test_layer_errors():
    with pytest.raises(InputError):
        FamilyInference(0)
    with pytest.raises(ShapeError):
        FamilyInference(3)(torch.zeros(1, 4, 2, 2))
    with pytest.raises(ShapeError):
        complete_family_code(torch.zeros(1, 2, 2, 2), torch.zeros(1, 2, 2, 2))


def test_complete_code_keeps_a_told_family_and_fills_an_unknown_one():
    given = torch.zeros(3, 2, 2, 2)
    given[0, 0] = 1.0  # Gaussian told
    given[1, 1] = 1.0  # pillbox told
    inferred = torch.tensor([[0.3, 0.6]] * 3).reshape(3, 2, 1, 1)
    out = complete_family_code(given, inferred)
    assert torch.equal(out[:2], given[:2])
    torch.testing.assert_close(out[2], inferred[2].expand(2, 2, 2))


def test_classes_and_loss():
    assert family_classes([{"psf_shape": "gaussian"}, {"psf_shape": "pillbox"}, {"psf_shape": "beta"},
                           {"psf_shape": None}, None]).tolist() == [0, 1, 2, -1, -1]
    assert FAMILY_CLASSES[:2] == ("gaussian", "pillbox")
    logits = torch.tensor([[5.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert float(family_loss(logits, torch.tensor([0, -1]))) < 0.02  # the unlabelled one does not count
    assert float(family_loss(logits, torch.tensor([1, -1]))) > 4.0
    assert float(family_loss(logits, torch.tensor([-1, -1]))) == 0.0


# ------------------------------------------------------------------ the model
def test_model_needs_the_family_input():
    with pytest.raises(InputError, match="psf_family_input"):
        DFDModel(Camera.preset("reference"), family_inference=True)


def test_told_family_is_used_and_unknown_one_is_inferred():
    m = _model()
    x1, x2 = _pair()
    feats, _ = m.features(x1, x2)
    with torch.no_grad():
        code, _ = m.refine.family((feats[:, :-2] - m.refine.feature_mean[:, :-2]) / m.refine.feature_std[:, :-2])
        unknown = m.set_psf_family(None)(x1, x2)[0]
        gaussian = m.set_psf_family("gaussian")(x1, x2)[0]
        # unknown (a zero code): the CNN's output is its output with the inferred soft code put in by hand
        assert float(feats[:, -2:].abs().max()) == 0.0
        soft = m.refine(feats)
        told_soft = m.refine.head(m.refine.act(m.refine.blocks(m.refine.stem(
            torch.cat([(feats[:, :-2] - m.refine.feature_mean[:, :-2]) / m.refine.feature_std[:, :-2],
                       (code.expand(-1, -1, *feats.shape[-2:]) - m.refine.feature_mean[:, -2:])
                       / m.refine.feature_std[:, -2:]], 1)))))
    torch.testing.assert_close(soft, told_soft)
    assert not torch.allclose(unknown, gaussian)
    assert 0.0 < float(code.sum()) < 1.0


def test_save_load_keeps_the_inference(tmp_path):
    m = _model()
    x1, x2 = _pair()
    m.save(tmp_path / "m")
    back = DFDModel.load(tmp_path / "m")
    assert back.refine.family is not None and back.refine.config()["family_inference"] is True
    with torch.no_grad():
        torch.testing.assert_close(back(x1, x2)[0], m(x1, x2)[0])


def test_onnx_export_matches_torch_unknown_and_told(tmp_path):
    from export.onnx_export import export_model

    m = _model()
    path = tmp_path / "fi.onnx"
    export_model(m, path)
    for family in (None, "pillbox"):
        rt = DepthRuntime(path, threads=1, psf_family=family)
        for h, w in ((160, 192), (96, 256)):  # the verdict pools each frame's own grid
            x1, x2 = _pair(h, w, seed=h)
            depth, conf, _ = rt.run(x1.numpy(), x2.numpy())
            with torch.no_grad():
                t_depth, t_conf, _ = m.set_psf_family(family)(x1, x2)
            np.testing.assert_allclose(depth, t_depth.numpy(), rtol=1e-3)  # export.verify's tolerances
            np.testing.assert_allclose(conf, t_conf.numpy(), atol=1e-3)


# ------------------------------------------------------------------ training
def test_featurizer_labels_every_sample_with_its_true_family():
    from training.config import ModelConfig
    from training.data import Featurizer

    fz = Featurizer(ModelConfig(psf_family_input=True, family_inference=True, hidden=8, blocks=1))
    x1, x2 = _pair(128, 128)
    batch = {"image_f1": torch.cat([x1] * 3), "image_f2": torch.cat([x2] * 3), "tile_depth": torch.ones(3, 1, 3, 3),
             "params": [{"psf_shape": "pillbox", "sample_seed": 1}, {"psf_shape": "beta", "sample_seed": 2}, None]}
    out = fz(batch)
    assert out["family_class"].tolist() == [1, 2, -1]


def test_config_rejects_inference_without_the_input():
    from training.config import ConfigError, load_config

    with pytest.raises(ConfigError, match="family_inference"):
        load_config(None, ["model.family_inference=true"])
    with pytest.raises(ConfigError, match="family_weight"):
        load_config(None, ["model.psf_family_input=true", "model.family_inference=true", "optim.family_weight=-1"])


def test_supervision_teaches_the_verdict():
    """Tiles whose feature 0 carries the class weakly and noisily: the image verdict, trained
    with the cross-entropy, names every image's class although single tiles often err."""
    g = torch.Generator().manual_seed(5)
    labels = torch.randint(3, (48,), generator=g)
    centres = torch.tensor([-1.0, 0.0, 1.0])
    x = torch.randn(48, 2, 6, 6, generator=g) * 1.0
    x[:, 0] += centres[labels][:, None, None]
    torch.manual_seed(0)
    layer = FamilyInference(in_channels=2, hidden=8)
    opt = torch.optim.Adam(layer.parameters(), lr=0.05)
    for _ in range(150):
        opt.zero_grad()
        loss = family_loss(layer(x)[1], labels)
        loss.backward()
        opt.step()
    with torch.no_grad():
        verdict = layer(x)[1].argmax(1)
        tile_alone = layer(x[..., :1, :1])[1].argmax(1)
    assert bool((verdict == labels).all())
    assert float((tile_alone == labels).double().mean()) < 0.9


def test_training_runs_with_the_inference(tmp_path, monkeypatch):
    import csv
    from pathlib import Path

    from tests.tiny_training import TINY
    from training.config import load_config
    from training.loop import train

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent))
    cfg = load_config(None, TINY + [f"out_dir={tmp_path / 'run'}", "final_eval=false", "model.psf_family_input=true",
                                    "model.family_inference=true"])
    train(cfg)
    rows = list(csv.DictReader((tmp_path / "run" / "train_log.csv").open()))
    assert "family_ce" in rows[0] and rows[0]["family_ce"] == "0"  # the stand-in records no psf_shape: no labels
    back = DFDModel.load(tmp_path / "run" / "model")
    assert back.refine.family is not None
