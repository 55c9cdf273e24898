"""benchmarks/bench_psf_model.py's pieces: the kernel error it scores a calibration by, and its tables."""

from __future__ import annotations

import torch

from benchmarks.bench_psf_model import STAGES, kernel_error, plane_table
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
            row[f"{k}_q"] = true * f
        rows.append(row)
    table, lines = plane_table(rows)
    cells = {r[0]: r[1] for r in table}
    # depth / true depth - 1 = true_q / q - 1
    assert cells["model"] == f"{100 * abs(1 / 1.04 - 1):.2f} %" and cells["told"] == "0.00 %"
    assert len(lines) == 4 and lines[0].startswith("- calibrated - profiled: per tile -0.9")
    assert lines[2].startswith("- calibrated - calibrated_shipped_scales: per tile -0.4")
