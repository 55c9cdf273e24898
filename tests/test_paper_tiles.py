"""benchmarks.paper_tiles: the per-tile diagnosis of the paper experiment's refined estimate."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks.paper_experiment import REFERENCE_FIELD, capture, paper_sensor
from benchmarks.paper_tiles import tile_errors
from export import export_model
from export.standin import analytic_model
from export.testing import session_onnx_model
from tdfd import Camera
from tdfd.illumination import CoherentIllumination
from tdfd.runtime import DepthRuntime

REF = Camera.preset("reference")


@pytest.fixture(scope="module")
def lit_pair():
    return capture(REF, CoherentIllumination(), 0.40, REFERENCE_FIELD, torch.Generator().manual_seed(0), paper_sensor())


def test_without_a_cnn_refined_and_analytic_tiles_agree(tmp_path, lit_pair):
    """The analytic stand-in's depth is its analytic depth: the two medians are one number,
    and a Gaussian-optics pattern at 40 cm is measured within 1 % on the pooled tiles."""
    path = export_model(analytic_model(), tmp_path / "analytic.onnx")
    pooled, refined, analytic, tiles = tile_errors(DepthRuntime(str(path)), *lit_pair, 0.40)
    assert tiles > 10
    assert refined == analytic
    assert abs(analytic) < 1.0 and abs(pooled) < 1.0


def test_a_cnn_that_changes_depth_shows_apart(tmp_path_factory, lit_pair):
    """The test model's random head shifts depth: the diagnosis shows the CNN's own part."""
    path, _ = session_onnx_model(tmp_path_factory)
    pooled, refined, analytic, tiles = tile_errors(DepthRuntime(str(path)), *lit_pair, 0.40)
    assert tiles > 10 and math.isfinite(pooled)
    assert abs(refined - analytic) > 0.5 and abs(analytic) < 1.0
