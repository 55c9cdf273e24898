#!/usr/bin/env python3
r"""Plant known bugs at the product's critical points and check that the test suite kills each.

A test suite that passes with the frames swapped or the gradient reversed protects nothing
there. This script plants one bug at a time (an exact text replacement in one file, which
must occur exactly once), runs the tests that guard that point, restores the file and
records whether the tests failed (*killed*) or passed (*survived*). Every planted bug
must be killed; the exit status is 0 only then.

::

    python3 dev.py python tools/mutation_check.py            # all, writes docs/BENCHMARKS.md
    .venv/bin/python tools/mutation_check.py --list          # the mutations and their tests
    .venv/bin/python tools/mutation_check.py --only crc-byte-order --no-write

The original file is restored after every mutant, on success, failure, Ctrl-C or SIGTERM;
a copy is kept beside it as ``<file>.mutation-backup`` while it is mutated, and a run
killed outright (SIGKILL, power loss) is repaired by the next run, which restores any such
backup first. Before the mutants, the union of their tests runs once unmutated and must
pass (otherwise "killed" would mean nothing). About 2-3 minutes on 2 cores.

Adding a mutation: append a :class:`Mutation` to :data:`MUTATIONS` with the smallest
realistic bug (a swapped argument, a flipped sign, a wrong byte order) and the *targeted*
tests that should catch it. If the code it names is refactored, the run stops with
"pattern not found": update ``old``/``new`` to the new code rather than deleting the entry.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BACKUP_SUFFIX = ".mutation-backup"
COMMAND = "python3 dev.py python tools/mutation_check.py"


@dataclass(frozen=True)
class Mutation:
    """One planted bug.

    Attributes:
        name: short identifier (``--only``).
        point: the critical point, for people.
        path: the file, relative to the repository root.
        old: exact text to replace (must occur exactly once in ``path``).
        new: the buggy text.
        tests: pytest arguments selecting the tests that must catch it.
        pending: why the mutation is not planted yet (``None`` when it is ready).
    """

    name: str
    point: str
    path: str
    old: str
    new: str
    tests: tuple[str, ...]
    pending: str | None = None


MUTATIONS: list[Mutation] = [
    Mutation(
        name="depth-cli-frame-order",
        point="frame order in `tdfd depth` (f2 passed as f1)",
        path="tdfd/depth_cli.py",
        old="res = rt(f1, f2, white_level=args.white_level)",
        new="res = rt(f2, f1, white_level=args.white_level)",
        tests=("tests/test_depth_cli.py::test_depth_of_rendered_planes_matches_the_truth",),
    ),
    Mutation(
        name="runtime-frame-order",
        point="frame order fed to the ONNX session (DepthRuntime.run)",
        path="tdfd/runtime.py",
        old="{INPUT_NAMES[0]: image_f1, INPUT_NAMES[1]: image_f2}",
        new="{INPUT_NAMES[0]: image_f2, INPUT_NAMES[1]: image_f1}",
        tests=("tests/test_runtime_pairs.py",),
    ),
    Mutation(
        name="pair-check-off",
        point="broken pairs (identical / black frames) vouched for by the runtime",
        path="tdfd/runtime.py",
        old="conf, problems = check_pairs(a, b, conf)",
        new="problems = (None,) * a.shape[0]",
        tests=("tests/test_runtime_pairs.py",),
    ),
    Mutation(
        name="eq6-sign",
        point="sign of paper eq. 6 (sigma1 - sigma2) in the depth solve",
        path="tdfd/optics/thin_lens.py",
        old="c = mu * camera.blur_scale_m_dpt * (p1 - p2)",
        new="c = mu * camera.blur_scale_m_dpt * (p2 - p1)",
        tests=("tests/test_dfd.py", "tests/test_dfd_mismatched_psf.py"),
    ),
    Mutation(
        name="gradient-ascent",
        point="gradient direction in training (loss ascended)",
        path="training/loop.py",
        old="            loss.backward()\n",
        new="            (-loss).backward()\n",
        tests=("tests/test_training_loop.py::test_training_lowers_the_validation_loss",),
    ),
    Mutation(
        name="crc-byte-order",
        point="CRC-16/ARC byte order of commands sent to the Lens Driver 4",
        path="tdfd/driver/protocol/framing.py",
        old='return payload + crc16_arc(payload).to_bytes(2, "little")',
        new='return payload + crc16_arc(payload).to_bytes(2, "big")',
        tests=("tests/test_driver_protocol.py",),
    ),
    Mutation(
        name="in-focus-power",
        point="in-focus ECVFL power 1/d_o + 1/d_s - 1/f0 (camera.py)",
        path="tdfd/camera.py",
        old="p = 1.0 / d + 1.0 / camera.sensor_distance_m - camera.fixed_power_dpt",
        new="p = -1.0 / d + 1.0 / camera.sensor_distance_m - camera.fixed_power_dpt",
        tests=("tests/test_camera.py", "tests/test_autofocus_controller.py"),
    ),
    Mutation(
        name="light-modem-line",
        point="the assist light's modem line level (tdfd/light: asserted = emitter on)",
        path="tdfd/light/serial_line.py",
        old='setattr, self.port, self.line, bool(level))',
        new='setattr, self.port, self.line, not level)',
        tests=("tests/test_light_serial.py", "tests/test_light_safety.py"),
    ),
]


# ----------------------------------------------------------------------------- file safety
def _backup_path(path: Path) -> Path:
    return path.with_name(path.name + BACKUP_SUFFIX)


def restore_leftovers() -> list[Path]:
    """Restore files from the backups a killed run left (before anything else)."""
    restored = []
    for m in MUTATIONS:
        if not m.path:
            continue
        target = ROOT / m.path
        backup = _backup_path(target)
        if backup.exists():
            os.replace(backup, target)
            restored.append(target)
    return restored


class _Planted:
    """Context manager: the mutated file inside the block, the original after it (always)."""

    def __init__(self, m: Mutation) -> None:
        self.m = m
        self.path = ROOT / m.path
        self.original = self.path.read_bytes()
        text = self.original.decode("utf-8")
        count = text.count(m.old)
        if count != 1:
            raise SystemExit(f"mutation {m.name}: pattern found {count} times in {m.path} (must be exactly once); "
                             f"update the entry in tools/mutation_check.py:\n  {m.old!r}")
        self.mutated = text.replace(m.old, m.new).encode("utf-8")

    def __enter__(self) -> "_Planted":
        backup = _backup_path(self.path)
        backup.write_bytes(self.original)
        self.path.write_bytes(self.mutated)
        return self

    def __exit__(self, *exc: object) -> None:
        self.path.write_bytes(self.original)
        _backup_path(self.path).unlink(missing_ok=True)
        assert self.path.read_bytes() == self.original, f"{self.path} was not restored"


def _raise_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


# ----------------------------------------------------------------------------- running tests
def run_tests(tests: tuple[str, ...], timeout_s: float) -> tuple[int | None, str, float]:
    """``(pytest exit code or None on timeout, last lines of output, seconds)``."""
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "--no-header", *tests]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        return None, out, time.perf_counter() - t0
    return proc.returncode, proc.stdout + proc.stderr, time.perf_counter() - t0


def _first_failure(output: str) -> str:
    for line in output.splitlines():
        m = re.match(r"(FAILED|ERROR) (\S+)", line)
        if m:
            return m.group(2).split("::", 1)[-1] if "::" in m.group(2) else m.group(2)
    return ""


def check(mutations: list[Mutation], timeout_s: float, verbose: bool) -> list[dict]:
    results = []
    for m in mutations:
        if m.pending:
            results.append({"m": m, "outcome": "pending", "detail": m.pending, "seconds": 0.0})
            print(f"[mutation] {m.name}: PENDING ({m.pending})", flush=True)
            continue
        with _Planted(m):
            rc, out, secs = run_tests(m.tests, timeout_s)
        if rc is None:
            outcome, detail = "killed", f"timeout after {timeout_s:.0f} s"
        elif rc in (1, 2):  # 1: tests failed; 2: collection error caused by the mutant
            outcome, detail = "killed", _first_failure(out) or f"pytest exit {rc}"
        elif rc == 0:
            outcome, detail = "SURVIVED", "all selected tests passed"
        else:
            outcome, detail = "error", f"pytest exit {rc}"
        if verbose or outcome != "killed":
            print(out[-3000:], flush=True)
        print(f"[mutation] {m.name}: {outcome} ({detail}, {secs:.0f} s)", flush=True)
        results.append({"m": m, "outcome": outcome, "detail": detail, "seconds": secs})
    return results


def table(results: list[dict]) -> str:
    rows = ["| mutation | critical point | file | planted bug | tests run | result | caught by | s |", "|---|" * 1 + "---|" * 7]
    for r in results:
        m = r["m"]
        bug = f"`{m.old.strip()}` -> `{m.new.strip()}`" if not m.pending else "-"
        tests = ", ".join(f"`{t}`" for t in m.tests) or "-"
        rows.append(f"| {m.name} | {m.point} | {('`' + m.path + '`') if m.path else '-'} | {bug} | {tests} | "
                    f"{r['outcome']} | {r['detail']} | {r['seconds']:.0f} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", default=None, help="run only this mutation (repeatable)")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--no-write", action="store_true", help="do not write docs/BENCHMARKS.md")
    ap.add_argument("--no-baseline", action="store_true", help="skip the unmutated run (not for recorded results)")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per test run (default 600)")
    ap.add_argument("-v", "--verbose", action="store_true", help="print pytest's output for every mutant")
    args = ap.parse_args(argv)

    if args.list:
        for m in MUTATIONS:
            state = f"PENDING: {m.pending}" if m.pending else " ".join(m.tests)
            print(f"{m.name:24s} {m.point}\n{'':24s} {state}")
        return 0
    signal.signal(signal.SIGINT, signal.default_int_handler)  # Ctrl-C, even where a shell ignored SIGINT
    for sig in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, _raise_interrupt)
    for p in restore_leftovers():
        print(f"[mutation] restored {p} from the backup a killed run left", flush=True)
    chosen = [m for m in MUTATIONS if args.only is None or m.name in args.only]
    unknown = set(args.only or ()) - {m.name for m in MUTATIONS}
    if unknown:
        ap.error(f"unknown mutation(s): {', '.join(sorted(unknown))}")
    for m in chosen:  # every pattern must be present before anything is planted
        if not m.pending:
            _Planted(m)

    t0 = time.perf_counter()
    try:
        if not args.no_baseline:
            union = tuple(dict.fromkeys(t for m in chosen for t in m.tests))
            rc, out, secs = run_tests(union, args.timeout)
            print(f"[mutation] baseline (unmutated): pytest exit {rc} in {secs:.0f} s", flush=True)
            if rc != 0:
                print(out[-5000:])
                print("[mutation] the unmutated tests fail: fix them first", file=sys.stderr)
                return 2
        results = check(chosen, args.timeout, args.verbose)
    except KeyboardInterrupt:
        print("\n[mutation] interrupted; every file is restored", file=sys.stderr)
        return 130
    wall = time.perf_counter() - t0
    planted = [r for r in results if r["outcome"] != "pending"]
    killed = sum(r["outcome"] == "killed" for r in planted)
    pending = [r["m"].name for r in results if r["outcome"] == "pending"]
    summary = (f"{killed} of {len(planted)} planted bugs killed"
               + (f"; not planted yet: {', '.join(pending)}" if pending else "")
               + f"; {wall:.0f} s in all including the unmutated baseline run.")
    print(table(results))
    print(summary)
    if not args.no_write and args.only is None:
        sys.path.insert(0, str(ROOT))
        from benchmarks.report import update_section

        body = ("Each row plants one bug at a critical point of the product (an exact text replacement, "
                "restored afterwards), runs the tests that guard that point, and records whether they fail "
                "(killed) or pass (SURVIVED). Every planted bug must be killed. The unmutated tests pass "
                "first (baseline).\n\n" + table(results) + "\n\n" + summary)
        update_section("mutation", "Mutation check: planted bugs the tests must kill", body, COMMAND)
        print("[mutation] wrote the 'mutation' section of docs/BENCHMARKS.md", flush=True)
    return 0 if killed == len(planted) else 1


if __name__ == "__main__":
    sys.exit(main())
