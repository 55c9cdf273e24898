"""Light safety in the autofocus loop: the light is off after every fault and interrupt, and the caps hold.

The bench half runs the real loop (emulated lens through the real driver, the guard on the
simulated clock); the hardware half runs :func:`run_hardware` with the light on pyserial's
``loop://`` (its CTS is the light line, read back) and a camera that sees the line.
"""

from __future__ import annotations

import numpy as np
import pytest

from tdfd import Camera
from tdfd.autofocus.estimators import AnalyticEstimator
from tdfd.autofocus.hardware import CaptureError, run_hardware
from tdfd.autofocus.messages import State
from tdfd.autofocus.sim import SimBench
from tdfd.driver import EmulatorServer, Faults, OptotuneLens
from tdfd.errors import TdfdError
from tdfd.light import LightLimits, SerialLineLight, SimulatedLight, open_serial_line
from tdfd.region_fusion import DEFAULT_MU_UNCERTAINTY

CAM = Camera.preset("reference")
HW = (192, 224)


@pytest.fixture(scope="module")
def analytic():
    return AnalyticEstimator(CAM)


class _Estimator:
    """Wraps an estimator; can raise, or answer with no confidence."""

    def __init__(self, inner, raise_exc=None, no_confidence=False):
        self.inner, self.raise_exc, self.no_confidence = inner, raise_exc, no_confidence
        self.camera, self.tile, self.stride = inner.camera, inner.tile, inner.stride

    def __call__(self, a, b):
        if self.raise_exc is not None:
            raise self.raise_exc
        d, c = self.inner(a, b)
        return d, (np.zeros_like(c) if self.no_confidence else c)


def _bench(estimator, light, controller=None, **kw):
    return SimBench(estimator=estimator, light=light, controller={"illumination": "coherent", **(controller or {})},
                    compute_s=0.001, readout_hw=HW, **kw)


def _watch_lens(bench, light):
    """Fail if the lens is ever commanded while the light is on (it is on for exposures only)."""
    command = bench.lens.command

    def guarded(*a, **k):
        assert not light.is_on, "the light was on during a lens command"
        return command(*a, **k)

    bench.lens.command = guarded


FAULTS = {
    "drop": Faults(drop=1.0, limit=2, seed=1),
    "bad_crc": Faults(bad_crc=1.0, limit=2, seed=1),
    "garbage": Faults(garbage=1.0, limit=3, seed=1),
    "late": Faults(late=1.0, late_s=0.2, limit=1, seed=1),
    "many": Faults(drop=0.3, bad_crc=0.2, garbage=0.2, late=0.1, late_s=0.05, seed=3),
    "disconnect": Faults(disconnect_after=5),
}


@pytest.mark.parametrize("kind", list(FAULTS))
def test_bench_light_off_after_every_emulator_fault(analytic, kind):
    light = SimulatedLight(CAM)
    with _bench(analytic, light, faults=FAULTS[kind]) as bench:
        _watch_lens(bench, light)
        recs = [bench.run_trial(d, "dfd", trial=i, uniform=True) for i, d in enumerate((0.4, 0.8))]
        assert not light.is_on and not bench.light_guard.is_on
        # on for lit exposures only: each switch-on is one exposure
        assert bench.light_guard.total_on_s == pytest.approx(light.switch_count * bench.timing.exposure_s)
    if kind == "disconnect":
        assert recs[-1].status == "failed"
    assert light.switch_count >= 1  # the faults hit a loop that did light the target


def _interrupt_sweep(bench, light, fail_on):
    """Raise KeyboardInterrupt at the k-th plant step (lens, capture, estimate, or inside a lit exposure),
    for every k of one trial; return the controller states interrupted."""
    states = set()
    k = 0
    while True:
        k += 1
        calls = {"n": 0}
        holder = {}
        make = bench.make_controller

        def make_ctrl(*a, **kw):
            holder["ctrl"] = make(*a, **kw)
            return holder["ctrl"]

        plant_factory = bench._plant

        def plant_with_interrupt(*a, **kw):
            plant = plant_factory(*a, **kw)
            for name in ("set_power", "capture", "estimate"):
                real = getattr(plant, name)

                def step(cmd, _real=real):
                    calls["n"] += 1
                    if calls["n"] == k:
                        raise KeyboardInterrupt
                    return _real(cmd)

                setattr(plant, name, step)
            expose = plant.camera.expose

            def expose_lit(t, _expose=expose):  # an interrupt while the light is on
                if fail_on == "exposure" and light.is_on and calls["n"] == k - 1:
                    raise KeyboardInterrupt
                return _expose(t)

            plant.camera.expose = expose_lit
            return plant

        bench.make_controller, bench._plant = make_ctrl, plant_with_interrupt
        try:
            bench.run_trial(0.55, "dfd", trial=k, uniform=True)
            finished = True
        except KeyboardInterrupt:
            finished = False
            states.add(holder["ctrl"].state)
        finally:
            bench.make_controller, bench._plant = make, plant_factory
        assert not light.is_on and not bench.light_guard.is_on, f"light on after an interrupt at step {k}"
        if finished:
            return states


def test_bench_light_off_after_keyboard_interrupt_in_every_state(analytic):
    light = SimulatedLight(CAM)
    with _bench(analytic, light) as bench:
        states = _interrupt_sweep(bench, light, "step")
        states |= _interrupt_sweep(bench, light, "exposure")
    # an estimate nobody trusts: the lit retry, then the pair's own estimate and its verification
    # frames, or (without the pair fall-back) the contrast search
    for options in ({}, {"pair_fallback": False}):
        light2 = SimulatedLight(CAM)
        with _bench(_Estimator(analytic, no_confidence=True), light2, options) as bench:
            states |= _interrupt_sweep(bench, light2, "step")
    assert {State.MOVE_F1, State.CAPTURE_F1, State.CAPTURE_F2, State.ESTIMATE, State.MOVE_FOCUS, State.VERIFY,
            State.CONTRAST} <= states


def test_bench_light_off_after_camera_failure_in_a_lit_exposure(analytic):
    light = SimulatedLight(CAM)
    with _bench(analytic, light) as bench:
        plant_factory = bench._plant

        def failing(*a, **kw):
            plant = plant_factory(*a, **kw)
            expose = plant.camera.expose

            def expose_or_fail(t):
                if light.is_on:
                    raise CaptureError("camera delivered no frame")
                return expose(t)

            plant.camera.expose = expose_or_fail
            return plant

        bench._plant = failing
        rec = bench.run_trial(0.5, "dfd", uniform=True)
        assert not light.is_on and bench.light_guard.switch_ons >= 2
        assert rec.status == "failed" and "CaptureError" in rec.reason  # a camera fault fails as in plain DFD


@pytest.mark.parametrize("exc", [RuntimeError("onnxruntime crashed"), TdfdError("bad frames")])
def test_bench_light_off_after_an_estimator_fault(analytic, exc):
    light = SimulatedLight(CAM)
    with _bench(_Estimator(analytic, raise_exc=exc), light) as bench:
        if isinstance(exc, TdfdError):
            rec = bench.run_trial(0.5, "dfd", uniform=True)
            assert rec.status == "failed" and "estimation failed" in rec.reason
        else:
            with pytest.raises(RuntimeError):
                bench.run_trial(0.5, "dfd", uniform=True)
        assert not light.is_on and light.switch_count == 2


def test_bench_caps_refuse_and_the_loop_goes_on_unlit(analytic):
    light = SimulatedLight(CAM)
    # 3 ms a request: one 2 ms lit exposure fits, the second is refused
    with _bench(analytic, light, light_limits=LightLimits(max_on_s=0.003)) as bench:
        rec = bench.run_trial(0.5, "dfd", uniform=True)
        assert bench.light_guard.refusals >= 1 and bench.light_guard.total_on_s <= 0.003 + 1e-9
        assert rec.extra["light"] is None and rec.method == "contrast"
        assert not light.is_on
    light = SimulatedLight(CAM)
    # duty cap: a lit pair and a lit verification frame (6 ms) fit in 0.7 % of 1 s only once per second
    with _bench(analytic, light, light_limits=LightLimits(max_on_s=1.0, max_duty=0.007, duty_window_s=1.0)) as bench:
        first = bench.run_trial(0.5, "dfd", uniform=True, idle_s=0.0)
        second = bench.run_trial(0.5, "dfd", uniform=True, idle_s=0.0)
        assert first.extra["light"] == "coherent" and second.extra["light"] is None
        assert bench.light_guard.refusals >= 1 and bench.light_guard.duty() <= 0.007 + 1e-9
        assert not light.is_on


# ----------------------------------------------------------------------------- hardware
class _LitCamera:
    """A camera on the emulated lens that sees the light line: a stripe pattern when CTS is on."""

    def __init__(self, device, port, depth_m=0.5, fail=None):
        import torch

        from tdfd.optics.render import render_at_power

        self.device, self.port, self.fail = device, port, fail
        flat = torch.full((1, 1) + HW, 0.4)
        lit = flat.clone()
        lit[..., 70:100] += 0.4
        lit[..., 130:150] += 0.4
        depth = torch.full_like(flat, depth_m)
        self.render = {s: (lambda p, s=s: render_at_power(CAM, s, depth, p)[0, 0].numpy()) for s in ()}
        self.scenes = {False: flat, True: lit}
        self.depth = depth
        self._render = render_at_power
        self.lit_reads = self.reads = 0
        self.rng = np.random.default_rng(0)

    def read(self):
        on = bool(self.port.cts)
        self.reads += 1
        self.lit_reads += on
        if self.fail is not None and on:
            raise self.fail
        img = self._render(CAM, self.scenes[on], self.depth, self.device.focal_power_dpt)[0, 0].numpy()
        return np.clip(img + 0.003 * self.rng.standard_normal(img.shape), 0, 1).astype(np.float32)

    def close(self):
        pass


def _hardware(analytic, fail=None, estimator=None, faults=None, **kw):
    port = open_serial_line("loop://", "rts")
    light = SerialLineLight(port, "rts", owns_port=True)
    srv = EmulatorServer(temperature_c=22.0).start()
    try:
        lens = OptotuneLens.open(srv.port, timeout_s=0.2)
        set_power = lens.set_focal_power_dpt

        def guarded(p, **kw):
            assert not port.cts, "the light was on during a lens command"
            return set_power(p, **kw)

        lens.set_focal_power_dpt = guarded
        cam = _LitCamera(srv.device, port, fail=fail)
        if faults is not None:
            srv.faults = faults
        try:
            # generous caps: the rendering camera is slow on a loaded machine, and the light stays on while
            # it renders (one lit read took over 10 s, the default duty window, at load 35; the caps have
            # their own tests)
            res = run_hardware(None, 0, estimator or analytic, camera=cam, lens=lens, light=light,
                               temperature_limits_c=(15.0, 25.0), settle_s=0.02,
                               light_limits=LightLimits(max_on_s=120.0, max_duty=1.0, duty_window_s=120.0), **kw)
        finally:
            lens.close()
        return res, cam, port, light
    finally:
        srv.stop()


def test_hardware_lit_focus_and_the_line_read_back(analytic):
    res, cam, port, light = _hardware(analytic)
    assert res.status == "focused" and res.frames <= 3 and cam.lit_reads == res.frames  # every frame lit
    assert port.cts is False and not light.is_on
    light.close()


def test_hardware_region_fit_counts_the_calibrated_mu_uncertainty(analytic, monkeypatch):
    """A calibrated camera file's mu uncertainty (tdfd autofocus --psf-family CAM.json) reaches the
    assist light's controller; without one the controller keeps its default."""
    import tdfd.autofocus.hardware as hw

    seen = []

    class Spy(hw.AssistedDFDController):
        def __init__(self, camera, **kw):
            super().__init__(camera, **kw)
            seen.append(self.region_mu_uncertainty)

    monkeypatch.setattr(hw, "AssistedDFDController", Spy)
    res, cam, port, light = _hardware(analytic, region_mu_uncertainty=0.003)
    assert res.status == "focused" and seen == [0.003] and port.cts is False
    light.close()
    res, cam, port, light = _hardware(analytic)
    light.close()
    assert seen == [0.003, DEFAULT_MU_UNCERTAINTY]


def test_hardware_light_off_after_camera_failure_and_interrupt(analytic):
    res, cam, port, light = _hardware(analytic, fail=CaptureError("USB camera unplugged"))
    assert cam.lit_reads >= 1 and port.cts is False and res.status in ("focused", "failed")
    light.close()
    res, cam, port, light = _hardware(analytic, fail=KeyboardInterrupt())
    assert res.status == "halted" and port.cts is False
    light.close()


def test_hardware_light_off_after_estimator_exception_and_lens_faults(analytic):
    with pytest.raises(RuntimeError):
        _hardware(analytic, estimator=_Estimator(analytic, raise_exc=RuntimeError("onnxruntime crashed")))
    for faults in (Faults(drop=1.0, limit=2, seed=1), Faults(bad_crc=1.0, limit=2, seed=2),
                   Faults(disconnect_after=4)):
        res, cam, port, light = _hardware(analytic, faults=faults)
        assert port.cts is False and not light.is_on
        light.close()
