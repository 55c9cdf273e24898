"""A tiny stand-in for ``data_synth.DefocusPairDataset`` used by the training tests.

Only the interface matters here (deterministic per ``(seed, index)``, dict samples with
``image_f1``, ``image_f2``, ``depth``, ``tile_depth``, ``params``, a batched path), so the
training pipeline can be tested quickly and independently of the real generator.
"""

from __future__ import annotations

import torch

from tdfd import Camera
from tdfd.forward import Defocus, DFDForward
from tdfd.grid import tile_true_depth
from tdfd.sensor import SensorModel
from tdfd.textures import fractal

#: Poisson-Gaussian noise of a 4000 e- well with 4 e- read noise, not quantised.
SENSOR = SensorModel(full_well_e=4000.0, read_noise_e=4.0, bits=16, black_level_dn=0.0, quantize=False)


class StandinDataset(torch.utils.data.Dataset):
    """Textured fronto-parallel planes, random PSF shape, Poisson-Gaussian noise."""

    def __init__(self, seed: int = 0, length: int = 1 << 20, size: tuple[int, int] = (96, 96), tile: int = 64,
                 stride: int = 32, camera: Camera | None = None, textureless_fraction: float = 0.1) -> None:
        self.seed, self.length, self.size = int(seed), int(length), tuple(size)
        self.tile, self.stride = tile, stride
        self.camera = camera or Camera.preset("reference")
        self.textureless_fraction = textureless_fraction

    def __len__(self) -> int:
        return self.length

    def _one(self, index: int) -> dict:
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + int(index))
        h, w = self.size
        tex = fractal((h, w), g, 1, beta=2.0)  # the library's 1/f texture in [0, 1]
        tex = (tex - tex.mean()) / tex.std()
        flat = float(torch.rand((), generator=g)) < self.textureless_fraction
        contrast = 0.002 if flat else 0.05 + 0.2 * float(torch.rand((), generator=g))
        sharp = (0.4 + contrast * tex).clamp(0.0, 1.0)
        near, far = self.camera.depth_range_m
        q = 1.0 / far + (1.0 / near - 1.0 / far) * float(torch.rand((), generator=g))
        depth = torch.full((1, 1, h, w), 1.0 / q)
        shape = ["gaussian", "pillbox", 4.0][int(torch.randint(3, (), generator=g))]
        frames = DFDForward(Defocus(self.camera, psf=shape), SENSOR)(sharp, depth, generator=g)
        noisy = [frames[:, 0:1], frames[:, 1:2]]
        return {"image_f1": noisy[0][0], "image_f2": noisy[1][0], "depth": depth[0],
                "tile_depth": tile_true_depth(depth, self.tile, self.stride)[0],
                "params": {"depth_m": 1.0 / q, "psf": str(shape), "textureless": flat}}

    def __getitem__(self, index: int) -> dict:
        return self._one(index)

    def batch(self, indices) -> dict:
        items = [self._one(int(i)) for i in indices]
        out = {k: torch.stack([it[k] for it in items]) for k in ("image_f1", "image_f2", "depth", "tile_depth")}
        out["params"] = [it["params"] for it in items]
        return out


def test_standin_is_deterministic():
    ds = StandinDataset(seed=3, size=(64, 64))
    a, b = ds[5], ds[5]
    assert torch.equal(a["image_f1"], b["image_f1"])
    assert a["tile_depth"].shape == (1, 1, 1)
    assert ds.batch([1, 2])["image_f2"].shape == (2, 1, 64, 64)
