"""The ONNX-vs-torch parity bounds every export test holds an exported model to."""


def assert_parity(report, cases: int) -> None:
    """``report`` (:func:`export.verify.verify_onnx`) has ``cases`` cases, all within the bounds:
    depth 1e-4 relative where the model is confident and 1e-3 everywhere, confidence 1e-3
    absolute, and more than half of the tiles confident (so the 1e-4 bound is not vacuous)."""
    assert len(report.cases) == cases
    assert report.worst_depth_rel <= 1e-4 and report.worst_confidence_abs <= 1e-3
    assert all(c.depth_rel_all <= 1e-3 and c.depth_analytic_rel_all <= 1e-3 for c in report.cases)
    assert sum(c.trusted_fraction for c in report.cases) / len(report.cases) > 0.5
