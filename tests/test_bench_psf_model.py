"""benchmarks/bench_psf_model.py's pieces: the kernel error it scores a calibration by, and its tables."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks.bench_psf_model import (BIAS_STAGE, STAGES, bound_line, family_table, kernel_error, plane_table,
                                        stages_of, structure_table)
from tdfd.errors import InputError
from tdfd.dfd.psf_hypotheses import PsfHypothesis
from tdfd.optics.aberrated_psf import PSFModel


def test_the_kernel_error_sees_the_aberrations_but_not_the_diffraction():
    lens = PSFModel(5.0, 0.6, 0.12, 1.0, 0.25)
    assert kernel_error(PsfHypothesis(5.0, 0.0, 0.12, 1.0, 0.25), lens) < 1e-12
    assert kernel_error(PsfHypothesis(5.0, 0.0, 0.12, 1.0, 0.25, 1.0), lens) == kernel_error(
        PsfHypothesis(5.0, 2.0, 0.12, 1.0, 0.25), lens)  # a common blur is left out of both
    near = kernel_error(PsfHypothesis(5.0, 0.0, 0.12, 1.0, 0.2), lens)
    far = kernel_error(PsfHypothesis("gaussian"), lens)
    assert 0.0 < near < far
    assert kernel_error(PsfHypothesis(5.0, 0.0, 0.12, 1.0, 0.25, 1.1), lens) > near  # the blur scale counts


def test_the_plane_table_scores_every_stage_against_the_truth():
    true = torch.full((25,), 2.0, dtype=torch.float64)
    rows = []
    for i in range(4):
        row = {"index": i, "true_q": true, "model_q": true * 1.04}
        for k, f in zip(STAGES, (1.02, 1.015, 1.01, 1.0)):
            row[f"{k}_q"], row[f"{k}_conf"] = true * f, torch.full((25,), 0.5, dtype=torch.float64)
        rows.append(row)
    table, lines = plane_table(rows)
    cells = {r[0]: r[1] for r in table}
    # depth / true depth - 1 = true_q / q - 1
    assert cells["model"] == f"{100 * abs(1 / 1.04 - 1):.2f} %" and cells["told"] == "0.00 %"
    assert len(lines) == 4 and lines[0].startswith("- calibrated - profiled: per tile -0.9")
    assert lines[2].startswith("- calibrated - calibrated_shipped_scales: per tile -0.4")


def test_the_bias_stage_is_scored_beside_the_others_where_it_was_run():
    true = torch.full((25,), 2.0, dtype=torch.float64)
    rows = []
    for i in range(4):
        row = {"index": i, "family": "dots", "true_q": true, "model_q": true * 1.04,
               "bound": torch.full((25,), 0.01, dtype=torch.float64)}
        for k, f in zip((*STAGES, BIAS_STAGE), (1.02, 1.015, 1.01, 1.0, 1.005)):
            row[f"{k}_q"], row[f"{k}_conf"] = true * f, torch.full((25,), 0.5, dtype=torch.float64)
        rows.append(row)
    assert stages_of(rows) == (*STAGES, BIAS_STAGE) and stages_of([{"calibrated_conf": true}]) == ("calibrated",)
    table, lines = plane_table(rows)
    assert [r[0] for r in table] == ["model", *STAGES, BIAS_STAGE]
    assert table[-1][1] == f"{100 * abs(1 / 1.005 - 1):.2f} %"
    assert len(lines) == 5 and lines[4].startswith(f"- {BIAS_STAGE} - calibrated: per tile -0.49 points")
    assert len(family_table(rows)[0]) == 3 + 1 + len(STAGES) + 1
    edge = torch.zeros(25, dtype=torch.bool)
    edge[:5] = True
    scenes = [{"layout": "slanted", "scene": 0, "true": true, "edge": edge, "model": true, "model_conf": true,
               **{k: torch.where(edge, true * 2, true * 1.01) for k in (*STAGES, BIAS_STAGE)},
               **{f"{k}_conf": torch.full((25,), 0.7, dtype=torch.float64) for k in (*STAGES, BIAS_STAGE)}}]
    (slanted,) = structure_table(scenes)
    assert len(slanted) == 3 + 1 + len(STAGES) + 1 and slanted[-1].startswith("1.00 %; 100 % at >= 0.5")
    assert slanted[2] == 20  # the tiles near an edge (here 100 % off) are left out


def test_the_family_table_divides_each_familys_error_by_its_own_bound():
    true = torch.full((25,), 2.0, dtype=torch.float64)
    rows = []
    for i, (family, err, bound) in enumerate((("dots", 0.01, 0.004), ("dots", 0.03, 0.004), ("stripes", 0.02, 0.02))):
        row = {"index": i, "family": family, "true_q": true, "model_q": true / (1 + err),
               "bound": torch.full((25,), bound / 0.6745, dtype=torch.float64)}
        for k in STAGES:
            row[f"{k}_q"], row[f"{k}_conf"] = true / (1 + err / 2), torch.full((25,), 0.5, dtype=torch.float64)
        rows.append(row)
    table = {r[0]: r for r in family_table(rows)}
    assert table["dots"][1] == 2 and table["stripes"][1] == 1
    assert table["dots"][2] == "0.40 %"  # 0.6745 x the median standard deviation
    # dots: the median of 25 tiles at 1 % and 25 at 3 % is 1 % (torch's lower median): 2.5x the bound
    assert table["dots"][3] == "1.00 % (2.5x)" and table["stripes"][3] == "2.00 % (1.0x)"
    assert table["stripes"][4] == "1.00 % (0.5x)"
    line = bound_line(rows)
    assert "per tile; each estimator's median per tile over it: model " in line


def test_psf_parameters_out_of_range_are_named_by_both_psf_classes():
    for bad in (dict(diffraction=math.inf), dict(angle=math.nan), dict(astig=0.5), dict(spherical=-0.5)):
        args = (5.0, bad.get("diffraction", 0.0), bad.get("astig", 0.1), bad.get("angle", 0.0),
                bad.get("spherical", 0.0))
        for cls in (PSFModel, PsfHypothesis):
            with pytest.raises(InputError, match="diffraction" if "diffraction" in bad else "astigmatism"):
                cls(*args)
    for cls in (PSFModel, PsfHypothesis):
        with pytest.raises(InputError, match="beta"):
            cls(math.inf)
        with pytest.raises(InputError, match="unknown PSF shape"):
            cls("disk")
