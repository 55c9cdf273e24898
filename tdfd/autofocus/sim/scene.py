r"""What the virtual camera looks at: a seeded procedural texture on a plane, or a user's image and depth map."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ...errors import InputError
from ..roi import Roi

__all__ = ["Scene", "BENCH_TEXTURE_FAMILIES"]


def _procedural_texture(hw: tuple[int, int], seed: int, albedo_contrast: float = 1.0) -> np.ndarray:
    """A seeded 1/f ("pink") noise texture in [0.1, 0.9] (fallback for :mod:`tdfd.textures`)."""
    h, w = hw
    rng = np.random.default_rng(seed)
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = 1.0 / f ** rng.uniform(0.8, 1.2)
    amp[0, 0] = 0.0
    phase = rng.uniform(0, 2 * np.pi, amp.shape)
    x = np.fft.irfft2(amp * np.exp(1j * phase), s=(h, w))
    x = (x - x.mean()) / (x.std() + 1e-12)
    return np.clip(0.5 + 0.16 * albedo_contrast * x, 0.1, 0.9)


#: texture families of the bench's default targets (textured surfaces; ``flat`` and
#: ``gradient`` are the texture-less cases, tested separately with ``uniform=True``).
BENCH_TEXTURE_FAMILIES = ("fractal", "bandlimited", "voronoi", "dead_leaves", "stripes", "checkers", "dots",
                          "line_art", "glyphs")


def _library_texture(hw: tuple[int, int], seed: int, families: Sequence[str] = BENCH_TEXTURE_FAMILIES
                     ) -> tuple[np.ndarray, str] | None:
    """A seeded texture from :func:`tdfd.textures.random_texture` (``None`` if unavailable)."""
    try:
        import torch

        from ...textures import random_texture
    except ImportError:
        return None
    g = torch.Generator().manual_seed(int(seed))
    tex, params = random_texture(g, hw, families=list(families), albedo=(0.5, 0.9), contrast=(0.3, 1.0))
    return tex[0, 0].double().numpy(), str(params.get("family", "texture"))


@dataclass
class Scene:
    """What the virtual camera looks at: sharp radiance and depth on the read-out window.

    Attributes:
        sharp: ``(H, W)`` all-in-focus linear radiance in [0, 1].
        depth_m: ``(H, W)`` object distance in metres.
        name: a label.
    """

    sharp: np.ndarray
    depth_m: np.ndarray
    name: str = "scene"

    def __post_init__(self) -> None:
        self.sharp = np.asarray(self.sharp, dtype=np.float64)
        self.depth_m = np.asarray(self.depth_m, dtype=np.float64)
        if self.sharp.ndim != 2 or self.sharp.shape != self.depth_m.shape:
            raise InputError(f"scene image and depth must be (H, W) of one shape, got {self.sharp.shape} and {self.depth_m.shape}")
        if not np.isfinite(self.depth_m).all() or (self.depth_m <= 0).any():
            raise InputError("scene depth must be finite and > 0")

    @property
    def planar(self) -> bool:
        """``True`` if the depth is one value everywhere (exact, fast rendering)."""
        return bool(self.depth_m.max() == self.depth_m.min())

    def roi_depth_m(self, roi: Roi) -> float:
        """The depth whose blur the ROI shows on average: the mean inverse depth, inverted (m)."""
        return float(1.0 / np.mean(1.0 / roi.crop(self.depth_m)))

    @classmethod
    def texture_plane(cls, hw: tuple[int, int], depth_m: float, seed: int = 0, uniform: bool = False,
                      families: Sequence[str] | None = None) -> "Scene":
        """A procedural texture (seeded) on a plane at ``depth_m``.

        Args:
            hw: ``(H, W)`` pixels.
            depth_m: plane distance (m).
            seed: texture seed.
            uniform: a texture-less grey plane instead.
            families: :mod:`tdfd.textures` families to draw from (default
                :data:`BENCH_TEXTURE_FAMILIES`); ``("pink",)`` is a built-in 1/f noise.
        """
        name = "uniform"
        families = tuple(families) if families else BENCH_TEXTURE_FAMILIES
        if uniform:
            sharp = np.full(hw, 0.5)
        else:
            lib = None if families == ("pink",) else _library_texture(hw, seed, families)
            sharp, name = lib if lib is not None else (_procedural_texture(hw, seed), "pink noise")
        return cls(sharp, np.full(hw, float(depth_m)), name=name)

    @classmethod
    def from_files(cls, image_path: str | Path, depth_path: str | Path, hw: tuple[int, int] | None = None,
                   linearise: bool = True) -> "Scene":
        """A user's image and depth map (``.npy`` in metres), resized to ``hw`` (default: the image's size).

        Args:
            image_path: any image OpenCV reads; converted to grey. 8/16-bit images are
                scaled by their white level.
            depth_path: ``.npy`` array ``(H, W)`` of distances in metres.
            hw: the read-out window size to resize both to.
            linearise: undo the sRGB gamma of an 8-bit image (linear radiance is needed).

        Raises:
            InputError: unreadable files or bad depth.
        """
        import cv2

        img = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"cannot read the scene image {image_path}")
        if img.ndim == 3:
            img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
        white = 65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype == np.uint8 else 1.0
        x = img.astype(np.float64) / white
        if linearise and img.dtype == np.uint8:
            x = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
        try:
            depth = np.load(str(depth_path)).astype(np.float64)
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read the scene depth {depth_path}: {exc}") from exc
        depth = np.squeeze(depth)
        if hw is None:
            hw = x.shape[:2]
        x = cv2.resize(x, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)
        depth = cv2.resize(depth, (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST)
        return cls(np.clip(0.05 + 0.9 * x, 0.0, 1.0), depth, name=Path(image_path).name)

    def at_distance(self, target_m: float, roi: Roi) -> "Scene":
        """The scene with its depth scaled so that the ROI sits at ``target_m`` (m)."""
        scale = target_m / self.roi_depth_m(roi)
        return Scene(self.sharp, self.depth_m * scale, self.name)
