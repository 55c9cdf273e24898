"""Synthesis throughput (issue 3: at least 50 pairs/s at 256 x 256 on the 2-core CPU) and the
accuracy budget of the renderer's layer spacing.

    .venv/bin/python -m benchmarks.bench_synthesis            # full run, rewrites its section
    .venv/bin/python -m benchmarks.bench_synthesis --quick    # fewer repeats, no accuracy table

Throughput is measured on complete samples (scene, illumination, both frames, breathing and
misregistration, sensor noise and quantisation, tile depth) from
``data_synth.DefocusPairDataset`` with the default training mix, three ways: the batch fast
path in the main process with 2 and 1 torch threads, and a ``DataLoader`` with 2 worker
processes (1 thread each). Each figure is the median over repeats of the steady-state rate.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import torch

from benchmarks.report import markdown_table, update_section

COMMAND = ".venv/bin/python -m benchmarks.bench_synthesis"


def _main_process_rate(ds, threads: int, block: int, repeats: int, offset: int) -> list[float]:
    torch.set_num_threads(threads)
    ds.batch(range(10_000_000, 10_000_000 + 4))  # warm-up (allocator, FFT plans)
    rates = []
    for r in range(repeats):
        start = offset + r * block
        t0 = time.perf_counter()
        ds.batch(range(start, start + block))
        rates.append(block / (time.perf_counter() - t0))
    return rates


def _loader_rate(ds, workers: int, block: int, batches: int, repeats: int, offset: int) -> list[float]:
    from data_synth import collate_pairs

    rates = []
    for r in range(repeats):
        start = offset + r * block * batches
        sub = torch.utils.data.Subset(ds, range(start, start + block * batches))
        loader = torch.utils.data.DataLoader(sub, batch_size=block, num_workers=workers, collate_fn=collate_pairs,
                                             prefetch_factor=2)
        stamps = []
        for _ in loader:
            stamps.append(time.perf_counter())
        # steady state: from the first batch's arrival to the last (worker start-up excluded)
        rates.append(block * (len(stamps) - 1) / (stamps[-1] - stamps[0]))
    return rates


def _cpu_per_layout(ds, count: int, offset: int) -> dict[str, list[float]]:
    torch.set_num_threads(1)
    out: dict[str, list[float]] = {}
    for i in range(offset, offset + count):
        t0 = time.process_time()
        s = ds[i]
        out.setdefault(s["params"]["layout"], []).append(time.process_time() - t0)
    return out


def _accuracy_rows(size: int = 256) -> list[list[str]]:
    """Layer-spacing accuracy on a full-range slanted plane (0.27 to 1.05 m across the image),
    against a 0.05 px reference: image error and analytic-DFD depth difference."""
    from tdfd import Camera
    from tdfd.dfd import FourierRatioDFD
    from tdfd.optics.render import defocus_layered_multi, sigma_map
    from tdfd.textures import fractal

    torch.set_num_threads(2)
    cam = Camera.preset("reference")
    dfd = FourierRatioDFD(cam, 64, 32)
    g = torch.Generator().manual_seed(0)
    y = torch.linspace(0, 1, size)[:, None]
    x = torch.linspace(0, 1, size)[None, :]
    q = (1 / 0.27 + (1 / 1.05 - 1 / 0.27) * (0.6 * x + 0.4 * y))[None, None]
    s1 = sigma_map(cam, 1.0 / q, cam.lens_powers_dpt[0])
    off = torch.tensor([0.0, -cam.sigma_difference_px])
    textures = [fractal(size, g, 1, beta=b) * 0.8 + 0.1 for b in (1.5, 2.0, 2.5)]
    rows = []
    for shape in ("gaussian", "pillbox"):
        errs: dict[tuple[float, bool], list[tuple[float, float]]] = {}
        for tex in textures:
            ref = defocus_layered_multi(tex, s1, off, shape, layer_spacing=0.05, max_layers=400)
            dref, _ = dfd(ref[:, 0], ref[:, 1])
            for sp in (0.25, 0.5, 1.0):
                for occ in (True, False):
                    out = defocus_layered_multi(tex, s1, off, shape, layer_spacing=sp, occlusion=occ)
                    dd, _ = dfd(out[:, 0], out[:, 1])
                    errs.setdefault((sp, occ), []).append(
                        (float((out - ref).abs().mean() / ref.mean()), float(((dd - dref) / dref).abs().mean())))
        for (sp, occ), v in errs.items():
            rows.append([shape, f"{sp:g}", "occluding" if occ else "gather",
                         f"{100 * statistics.mean(a for a, _ in v):.2f} %", f"{100 * statistics.mean(b for _, b in v):.2f} %"])
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="benchmarks.bench_synthesis")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--quick", action="store_true", help="fewer repeats, no accuracy table, no doc update")
    p.add_argument("--wait-idle", type=float, default=600.0,
                   help="wait up to this many seconds for the 1-minute load average to drop below --idle-load "
                        "(the machine is shared; default 600)")
    p.add_argument("--idle-load", type=float, default=1.0)
    args = p.parse_args(argv)
    t_wait = time.monotonic()
    while os.getloadavg()[0] >= args.idle_load and time.monotonic() - t_wait < args.wait_idle:
        time.sleep(5.0)
    from data_synth import DefocusPairDataset

    size = args.size
    ds = DefocusPairDataset(size=size, seed=0)
    block = 32
    reps = 2 if args.quick else 5
    load0 = os.getloadavg()[0]
    loader = _loader_rate(ds, 2, block, 4 if args.quick else 6, 2 if args.quick else 3, 2000)
    main2 = _main_process_rate(ds, 2, block, reps, 0)
    main1 = _main_process_rate(ds, 1, block, reps, 1000)
    cpu = _cpu_per_layout(ds, 40 if args.quick else 120, 5000)
    load1 = os.getloadavg()[0]
    med = {k: statistics.median(v) for k, v in (("main2", main2), ("main1", main1), ("loader", loader))}
    allcpu = [t for v in cpu.values() for t in v]
    print(f"synthesis at {size}x{size}: main process 2 threads {med['main2']:.1f} pairs/s, 1 thread "
          f"{med['main1']:.1f} pairs/s, DataLoader 2 workers {med['loader']:.1f} pairs/s; "
          f"CPU {1e3 * statistics.mean(allcpu):.1f} ms/pair (1 thread); load average {load0:.2f} -> {load1:.2f}")
    for k, v in sorted(cpu.items()):
        print(f"  {k:8s} {len(v):4d} samples  CPU median {1e3 * statistics.median(v):6.1f} ms/pair")
    if args.quick:
        return 0
    acc = _accuracy_rows(size)
    for r in acc:
        print("  accuracy", r)
    best = max(med.values())
    rows = [
        ["`dataset.batch(indices)`, main process, `torch.set_num_threads(2)`", f"{med['main2']:.1f}",
         ", ".join(f"{r:.1f}" for r in main2)],
        ["`dataset.batch(indices)`, main process, 1 thread", f"{med['main1']:.1f}", ", ".join(f"{r:.1f}" for r in main1)],
        ["`DataLoader(dataset, batch_size=32, num_workers=2, collate_fn=collate_pairs)`", f"{med['loader']:.1f}",
         ", ".join(f"{r:.1f}" for r in loader)],
    ]
    layout_rows = [[k, len(v), f"{1e3 * statistics.median(v):.1f}", f"{1e3 * statistics.mean(v):.1f}"]
                   for k, v in sorted(cpu.items())]
    verdict = "meets" if best >= 50 else "does NOT meet"
    body = f"""
Complete training pairs at {size} x {size} from `data_synth.DefocusPairDataset` (default mix:
15 % fronto-parallel planes, 25 % slanted planes, 40 % piecewise-planar layouts with occlusion
edges, 20 % smooth surfaces; 30 % with active illumination; random PSF shape, diffraction and
aberration; breathing, misregistration; Poisson-Gaussian sensor, 8-12 bit), everything
included: scene and textures, both frames, warp, noise, quantisation, tile depth. Rates are
medians over repeats (each value: one block of {block} pairs, or for the DataLoader the
steady state of one loader, worker start-up excluded).

{markdown_table(["path", "pairs/s (median)", "repeats"], rows)}

Best: **{best:.1f} pairs/s**, which {verdict} the 50 pairs/s target. Use a `DataLoader` with
`num_workers=2` (each worker renders with one torch thread, so both cores are busy; this is
the configuration of the target). The main-process batch path is limited by one process: with
`torch.set_num_threads(2)` it gains little (a sample is many small tensor operations), and
when other processes share the cores its OpenMP threads wait on each other and it can fall
far below the 1-thread rate, so prefer 1 thread per process. The machine is shared with other
sessions: the 1-minute load average was {load0:.2f} at the start and {load1:.2f} at the end
of the run (the run waits up to 10 minutes for the load to drop below 1), so these rates are
lower bounds for an idle machine. Single-thread CPU time per pair (`time.process_time`; the
sum over both cores is what bounds the throughput):

{markdown_table(["layout", "samples", "CPU ms/pair (median)", "CPU ms/pair (mean)"], layout_rows)}

Mean over all: {1e3 * statistics.mean(allcpu):.1f} ms of CPU per pair.

Accuracy budget of the renderer's layer spacing (`SynthConfig.layer_spacing`, default 0.5 px
of sigma): a full-range slanted plane (0.27 m to 1.05 m across the image, the steepest case)
rendered with spacing 0.25 / 0.5 / 1 px versus a 0.05 px reference, mean over three 1/f
textures: mean absolute image error relative to the mean level, and the mean relative
difference of the analytic DFD depth (`FourierRatioDFD`, 64/32 tiles) on the two renders.
Both frames share one layer decomposition, so the layering error is the same in both frames.
The image error falls with the spacing as expected; the DFD depth differences are dominated by
the estimator's sensitivity on the nearest tiles (largest blur), hence not monotonic for the
Gaussian. 0.5 px keeps both below 1 %, well under the DFD's own errors, at half the layers of
0.25 px.

{markdown_table(["PSF", "spacing (px)", "mode", "image error", "DFD depth difference"], acc)}
"""
    update_section("synthesis", "Procedural pair synthesis (data_synth)", body, COMMAND)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
