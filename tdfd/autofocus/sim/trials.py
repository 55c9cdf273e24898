r"""One bench trial's record (the report's raw material) and the seeded target distances of a run."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...errors import InputError

__all__ = ["TrialRecord", "trial_depths"]


@dataclass
class TrialRecord:
    """One autofocus trial on the bench (the contract fields plus what the report summary needs).

    Attributes:
        target_depth_m: true distance of the ROI (m).
        estimated_depth_m: the DFD estimate (m), ``None`` without one.
        ideal_power_dpt: in-focus ECVFL power of the target (dpt).
        final_power_dpt: the lens's optical power when focus was declared (or at the end
            of a failed trial) (dpt).
        residual_blur_px: ``|r_b|`` at ``final_power_dpt`` (px).
        frames: frames captured.
        lens_commands: set-point commands sent.
        time_ms: simulated time from the request to focus (or to the failure) (ms).
        method: ``"dfd"`` or ``"contrast"``: the method that set the final power.
        requested: the method asked for.
        status: ``"focused"``, ``"failed"``, ...
        reason: failure or fall-back reason, ``None`` if none.
        confidence: ROI confidence of the DFD estimate.
        compute_ms: estimator time charged (ms).
        verified: verification outcome, ``None`` if not verified.
        trial: index.
        scene: the scene's name (texture family).
        evidence: what declared the focus (``"uncertainty"``, ``"verification"``,
            ``"contrast"``), ``None`` if focus was not declared.
        uncertainty_px: the DFD estimate's own uncertainty as a blur radius (px).
        dfd_blur_px: ``|r_b|`` at the in-focus power of the first DFD estimate (px): whether
            that estimate was right, whatever the controller then did.
        refine_count: further DFD steps after failed verifications.
        psf: the simulated optics' PSF.
        blur_measurements: relative-blur measurements the controller's evidence took (each
            charged to ``time_ms``).
    """

    target_depth_m: float
    estimated_depth_m: float | None
    ideal_power_dpt: float
    final_power_dpt: float | None
    residual_blur_px: float | None
    frames: int
    lens_commands: int
    time_ms: float | None
    method: str
    requested: str = "dfd"
    status: str = "focused"
    reason: str | None = None
    confidence: float | None = None
    compute_ms: float | None = None
    verified: bool | None = None
    trial: int = 0
    scene: str = ""
    evidence: str | None = None
    uncertainty_px: float | None = None
    dfd_blur_px: float | None = None
    refine_count: int = 0
    psf: str = ""
    blur_measurements: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def declared(self) -> bool:
        """The controller declared focus."""
        return self.status == "focused"

    @property
    def in_focus(self) -> bool:
        """Focus declared and residual blur radius under 1 px."""
        return self.declared and self.residual_blur_px is not None and self.residual_blur_px < 1.0

    @property
    def declared_out_of_focus(self) -> bool:
        """Focus declared with a residual blur radius of 1 px or more: the failure the controller must not make."""
        return self.declared and not self.in_focus

    @property
    def withheld_correct(self) -> bool:
        """The first DFD estimate was in focus, but the controller did not declare focus on it at once
        (it verified and refined, searched by contrast, or ended without declaring)."""
        if self.dfd_blur_px is None or self.dfd_blur_px >= 1.0:
            return False
        return not (self.declared and self.evidence in ("uncertainty", "verification") and self.refine_count == 0)


def trial_depths(n: int, seed: int = 0, depth_range_m: tuple[float, float] = (0.3, 1.0)) -> list[float]:
    """``n`` target distances spread across ``depth_range_m``: stratified, uniform in inverse depth, seeded.

    Example:
        >>> d = trial_depths(4, seed=0)
        >>> len(d), all(0.3 <= x <= 1.0 for x in d)
        (4, True)
    """
    if n < 1:
        raise InputError(f"need at least one trial, got {n}")
    near, far = depth_range_m
    q_lo, q_hi = 1.0 / far, 1.0 / near
    rng = np.random.default_rng(seed)
    u = (np.arange(n) + rng.uniform(0.0, 1.0, n)) / n
    q = q_lo + u * (q_hi - q_lo)
    rng.shuffle(q)
    return [float(1.0 / x) for x in q]
