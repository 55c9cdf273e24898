"""The autofocus report (CONTRACT.md section 3) and its human-readable table.

``tdfd autofocus ... --json FILE`` writes ``{"trials": [...], "summary": {...}}``. Each
trial holds the contract's keys (:data:`TRIAL_KEYS`) plus :data:`EXTRA_TRIAL_KEYS`
(whether focus was declared, on what evidence, whether a verification frame confirmed
it); everything else (per-method statistics, the declaration's reliability, the bench
settings, and a note for every trial that failed or fell back, with its reason) goes
into ``summary``.

Example:
    >>> from tdfd.autofocus.sim.trials import TrialRecord
    >>> r = TrialRecord(0.5, 0.501, 2.0, 2.004, 0.02, 2, 3, 55.1, "dfd")
    >>> sorted(trial_entry(r)) == sorted(TRIAL_KEYS + EXTRA_TRIAL_KEYS)
    True
    >>> summarise([r])["methods"]["dfd"]["success_rate"]
    1.0
"""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path
from typing import Any, Iterable, Sequence

__all__ = ["TRIAL_KEYS", "EXTRA_TRIAL_KEYS", "trial_entry", "summarise", "build_report", "write_report", "format_table",
           "format_summary", "MAX_DFD_FRAMES"]

#: the keys of one trial, CONTRACT.md section 3, in order.
TRIAL_KEYS = ("target_depth_m", "estimated_depth_m", "ideal_power_dpt", "final_power_dpt", "residual_blur_px",
              "frames", "lens_commands", "time_ms", "method")
#: keys added to each trial beyond the contract (docs/ARCHITECTURE.md): ``declared`` (the
#: controller declared focus), ``evidence`` (``"uncertainty"``, ``"verification"``,
#: ``"refined"``, ``"contrast"`` or ``null``), ``verified`` (the last verification frame's verdict, ``null``
#: if none was taken).
EXTRA_TRIAL_KEYS = ("declared", "evidence", "verified")
#: frame budget of the DFD success criterion (issue 7: in focus with at most 3 frames).
MAX_DFD_FRAMES = 3


def _num(x: Any, nd: int = 6) -> Any:
    if x is None:
        return None
    if isinstance(x, bool):
        return x
    if isinstance(x, int):
        return x
    f = float(x)
    return round(f, nd) if math.isfinite(f) else None


def trial_entry(record: Any) -> dict[str, Any]:
    """The trial object for a :class:`~tdfd.autofocus.sim.trials.TrialRecord`: :data:`TRIAL_KEYS` then :data:`EXTRA_TRIAL_KEYS`."""
    return {
        "target_depth_m": _num(record.target_depth_m),
        "estimated_depth_m": _num(record.estimated_depth_m),
        "ideal_power_dpt": _num(record.ideal_power_dpt),
        "final_power_dpt": _num(record.final_power_dpt),
        "residual_blur_px": _num(record.residual_blur_px),
        "frames": int(record.frames),
        "lens_commands": int(record.lens_commands),
        "time_ms": _num(record.time_ms, 3),
        "method": str(record.method),
        "declared": record.status == "focused",
        "evidence": getattr(record, "evidence", None),
        "verified": getattr(record, "verified", None),
    }


def _stats(values: Sequence[float]) -> dict[str, Any]:
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    if not v:
        return {"median": None, "mean": None, "max": None, "min": None}
    return {"median": _num(statistics.median(v), 3), "mean": _num(statistics.fmean(v), 3), "max": _num(max(v), 3),
            "min": _num(min(v), 3)}


def summarise(records: Sequence[Any], settings: dict[str, Any] | None = None) -> dict[str, Any]:
    """Per requested method: success rate (focus declared and residual blur < 1 px), frames,
    lens commands, bench time, residual blur, fall-backs and failures; plus notes and settings.

    The declaration's reliability: ``declared_out_of_focus`` counts trials where focus was
    declared with a residual blur of 1 px or more (the controller must not do that), and for
    DFD ``withheld_correct`` counts trials whose first DFD estimate was in focus but was not
    declared at once (``TrialRecord.withheld_correct``), out of ``correct_dfd_estimates``.

    For DFD, ``success_rate_max3_frames`` also requires at most :data:`MAX_DFD_FRAMES` frames.
    With both methods, ``contrast_to_dfd_frames`` is the ratio of their median frame counts.
    """
    methods: dict[str, Any] = {}
    for m in dict.fromkeys(r.requested for r in records):
        rs = [r for r in records if r.requested == m]
        n = len(rs)
        ok = [r for r in rs if r.in_focus]
        entry: dict[str, Any] = {
            "trials": n,
            "in_focus": len(ok),
            "success_rate": _num(len(ok) / n, 4) if n else None,
            "frames": _stats([r.frames for r in rs]),
            "lens_commands": _stats([r.lens_commands for r in rs]),
            "time_ms": _stats([r.time_ms for r in rs if r.status == "focused"]),
            "residual_blur_px": _stats([r.residual_blur_px for r in rs]),
            "fallbacks": sum(1 for r in rs if r.requested == "dfd" and r.method == "contrast"),
            "failures": sum(1 for r in rs if r.status != "focused"),
            "declared": sum(1 for r in rs if r.status == "focused"),
            "declared_out_of_focus": sum(1 for r in rs if r.status == "focused" and not r.in_focus),
            "declared_out_of_focus_rate": _num(sum(1 for r in rs if r.status == "focused" and not r.in_focus) / n, 4)
            if n else None,
            "evidence": {k: sum(1 for r in rs if getattr(r, "evidence", None) == k)
                         for k in ("uncertainty", "verification", "refined", "contrast")},
        }
        if m == "dfd":
            good = [r for r in ok if r.frames <= MAX_DFD_FRAMES]
            entry["success_rate_max3_frames"] = _num(len(good) / n, 4) if n else None
            comp = [r.compute_ms for r in rs if r.compute_ms is not None]
            entry["compute_ms"] = _stats(comp)
            conf = [r.confidence for r in rs if r.confidence is not None]
            entry["confidence"] = _stats(conf)
            judged = [r for r in rs if getattr(r, "dfd_blur_px", None) is not None and r.dfd_blur_px < 1.0]
            withheld = sum(1 for r in judged if r.withheld_correct)
            entry["correct_dfd_estimates"] = len(judged)
            entry["withheld_correct"] = withheld
            entry["withheld_correct_rate"] = _num(withheld / len(judged), 4) if judged else None
        methods[m] = entry
    summary: dict[str, Any] = {"trials": len({r.trial for r in records}), "methods": methods}
    if "dfd" in methods and "contrast" in methods:
        fd, fc = methods["dfd"]["frames"]["median"], methods["contrast"]["frames"]["median"]
        td, tc = methods["dfd"]["time_ms"]["median"], methods["contrast"]["time_ms"]["median"]
        summary["contrast_to_dfd_frames"] = _num(fc / fd, 3) if fd and fc else None
        summary["contrast_to_dfd_time"] = _num(tc / td, 3) if td and tc else None
    notes = []
    for i, r in enumerate(records):
        if r.status != "focused" or r.reason or r.method != r.requested:
            notes.append({"index": i, "trial": r.trial, "requested": r.requested, "method": r.method,
                          "status": r.status, "reason": r.reason, "scene": getattr(r, "scene", "")})
        elif not r.in_focus:
            notes.append({"index": i, "trial": r.trial, "requested": r.requested, "method": r.method,
                          "status": "out of focus", "reason": f"residual blur {r.residual_blur_px:.2f} px",
                          "scene": getattr(r, "scene", "")})
    summary["notes"] = notes
    if settings:
        summary["settings"] = settings
    return summary


def build_report(records: Sequence[Any], settings: dict[str, Any] | None = None) -> dict[str, Any]:
    """``{"trials": [...], "summary": {...}}`` (CONTRACT.md section 3)."""
    return {"trials": [trial_entry(r) for r in records], "summary": summarise(records, settings)}


def write_report(path: str | Path, records: Sequence[Any], settings: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write :func:`build_report` as JSON to ``path`` (parents created); return the report."""
    report = build_report(records, settings)
    path = Path(path)
    if path.parent and not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")
    return report


def _fmt(x: Any, spec: str) -> str:
    if x is None:
        return "-"
    try:
        return format(float(x), spec)
    except (TypeError, ValueError):
        return str(x)


def format_table(records: Iterable[Any]) -> str:
    """A fixed-width table, one line per trial, for the terminal ("declared on": the evidence focus
    was declared on, ``-`` if it was not declared)."""
    head = (f"{'#':>3} {'method':<9} {'target m':>8} {'est. m':>7} {'ideal dpt':>9} {'final dpt':>9} "
            f"{'blur px':>7} {'frames':>6} {'cmds':>4} {'time ms':>8} {'declared on':<12} result")
    lines = [head, "-" * len(head)]
    for r in records:
        if r.status != "focused":
            result = f"FAILED: {r.reason}"
        elif r.in_focus:
            result = "in focus"
        else:
            result = "OUT OF FOCUS"
        if r.method != r.requested:
            result += f" (fell back to {r.method}: {r.reason})"
        elif r.reason and r.status == "focused":
            result += f" ({r.reason})"
        method = r.requested if r.method == r.requested else f"{r.requested}>{r.method[:3]}"
        scene = getattr(r, "scene", "")
        if scene and not r.in_focus:
            result += f" [{scene}]"
        lines.append(f"{r.trial:>3} {method:<9} {_fmt(r.target_depth_m, '8.3f')} {_fmt(r.estimated_depth_m, '7.3f'):>7} "
                     f"{_fmt(r.ideal_power_dpt, '9.3f')} {_fmt(r.final_power_dpt, '9.3f')} "
                     f"{_fmt(r.residual_blur_px, '7.2f')} {r.frames:>6d} {r.lens_commands:>4d} "
                     f"{_fmt(r.time_ms, '8.1f')} {getattr(r, 'evidence', None) or '-':<12} {result}")
    return "\n".join(lines)


def format_summary(summary: dict[str, Any]) -> str:
    """The summary as a few readable lines."""
    out = []
    for m, s in summary["methods"].items():
        rate = s["success_rate"]
        line = (f"{m:<9} in focus (blur < 1 px): {s['in_focus']}/{s['trials']} ({100 * (rate or 0):.0f} %)"
                f" | frames median {_fmt(s['frames']['median'], 'g')}, max {_fmt(s['frames']['max'], 'g')}"
                f" | time median {_fmt(s['time_ms']['median'], '.1f')} ms, max {_fmt(s['time_ms']['max'], '.1f')} ms"
                f" | blur median {_fmt(s['residual_blur_px']['median'], '.2f')} px")
        if m == "dfd":
            line += (f" | <= {MAX_DFD_FRAMES} frames and in focus: {100 * (s['success_rate_max3_frames'] or 0):.0f} %"
                     f" | fall-backs {s['fallbacks']}")
        if s["failures"]:
            line += f" | FAILED {s['failures']}"
        line += f" | declared out of focus {s['declared_out_of_focus']}"
        if s.get("withheld_correct") is not None:
            line += f" | correct estimates withheld {s['withheld_correct']}/{s['correct_dfd_estimates']}"
        out.append(line)
    if summary.get("contrast_to_dfd_frames"):
        out.append(f"contrast AF needs {summary['contrast_to_dfd_frames']:.2f}x the frames of DFD "
                   f"and {_fmt(summary.get('contrast_to_dfd_time'), '.2f')}x its time")
    return "\n".join(out)
