r"""Training scenes: depth layouts, textured surfaces and active illumination.

A scene is a sharp (all-in-focus) radiance image and a depth map in metres, both
``(1, 1, H, W)``, built from a :class:`torch.Generator`:

* **Depth** (inverse depth ``q = 1/d`` sampled uniformly over the camera's range widened by
  a margin; blur is linear in ``q``, paper eq. 4):

  - ``plane``: a fronto-parallel plane;
  - ``slanted``: a tilted plane, whose inverse depth is affine in image coordinates (a
    3-D plane seen through a pinhole);
  - ``smooth``: a tilted plane plus a smooth random relief (1/f^4 noise);
  - ``layout``: piecewise-planar: a background (plane or slanted) and 1 to
    ``max_objects`` foreground objects (ellipses, rotated rectangles, convex polygons,
    bars, blobs), each a fronto-parallel or slanted plane with its own texture; their
    outlines are occlusion edges (depth jumps, handled by the layered renderer).

* **Albedo**: a :mod:`tdfd.textures` texture per surface with random albedo and contrast;
  object outlines are anti-aliased in the albedo (a boundary pixel mixes both surfaces)
  while the depth map assigns each pixel to the surface covering most of it.

* **Illumination** (:mod:`tdfd.illumination`): none (ambient only), the coherent
  conditioned pattern (optionally with diffraction orders and speckle) or the incoherent
  projector, with random mask patterns specified in physical units. An actively lit scene
  is often a texture-less target (the paper's black page). Radiance is
  ``albedo * (ambient + pattern)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from tdfd import Camera
from tdfd.illumination import CoherentIllumination, MaskPattern, ProjectorIllumination, illuminate
from tdfd.textures import fractal, random_texture

from .params import SynthConfig, bernoulli, choice, inverse_depth_range, log_uniform, randint, uniform

__all__ = ["Scene", "make_scene", "det_mean", "depth_plane", "depth_slanted", "depth_smooth", "region_shape",
           "draw_illumination"]


@dataclass
class Scene:
    """A synthetic scene.

    Attributes:
        radiance: ``(1, 1, H, W)`` sharp linear radiance.
        depth: ``(1, 1, H, W)`` object distance in metres.
        layout: the depth layout name.
        params: what made it (plain values; nested lists/dicts for the details).
    """

    radiance: torch.Tensor
    depth: torch.Tensor
    layout: str
    params: dict


def det_mean(x: torch.Tensor) -> float:
    """Mean of a tensor in float64 numpy (pairwise summation): the same bits whatever the
    number of torch threads (torch's parallel reductions are not), so that values derived
    from it (random ranges, exposure) reproduce exactly in DataLoader workers."""
    return float(np.mean(x.detach().double().cpu().numpy()))


# ----------------------------------------------------------------------------- depth
def _grid(h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised coordinates ``y`` (H, 1), ``x`` (1, W) in [0, 1]."""
    y = torch.linspace(0.0, 1.0, h)[:, None]
    x = torch.linspace(0.0, 1.0, w)[None, :]
    return y, x


def depth_plane(h: int, w: int, q: float) -> torch.Tensor:
    """Fronto-parallel plane at inverse depth ``q`` (1/m): inverse-depth map ``(1, 1, H, W)``."""
    return torch.full((1, 1, h, w), float(q))


def depth_slanted(h: int, w: int, q00: float, q01: float, q10: float) -> torch.Tensor:
    """A tilted plane through inverse depths ``q00`` (top-left), ``q01`` (top-right) and
    ``q10`` (bottom-left): ``q`` is affine in image coordinates. Returns ``(1, 1, H, W)``."""
    y, x = _grid(h, w)
    return (q00 + (q01 - q00) * x + (q10 - q00) * y)[None, None]


def _draw_slant(g: torch.Generator, q_lo: float, q_hi: float, spread: float) -> tuple[float, float, float, float]:
    qc = uniform(g, q_lo, q_hi)
    s = uniform(g, 0.0, spread) * (q_hi - q_lo)
    corners = [min(q_hi, max(q_lo, qc + uniform(g, -s, s))) for _ in range(3)]
    return qc, corners[0], corners[1], corners[2]


def depth_smooth(h: int, w: int, g: torch.Generator, base: torch.Tensor, amplitude: float) -> torch.Tensor:
    """``base`` plus a smooth random relief of peak-to-peak ``amplitude`` (inverse depth)."""
    relief = fractal((h, w), g, 1, beta=uniform(g, 3.5, 5.0)) - 0.5
    return base + amplitude * relief


# ----------------------------------------------------------------------------- shapes
def region_shape(g: torch.Generator, h: int, w: int) -> tuple[torch.Tensor, dict]:
    """A random object outline as a signed distance map ``(1, 1, H, W)`` in px (> 0 inside)."""
    kind = choice(g, ("ellipse", "rect", "polygon", "bar", "blob"), (0.25, 0.25, 0.2, 0.15, 0.15))
    n = min(h, w)
    yy = torch.arange(h, dtype=torch.float32)[:, None] + 0.5
    xx = torch.arange(w, dtype=torch.float32)[None, :] + 0.5
    cy, cx = uniform(g, 0.1, 0.9) * h, uniform(g, 0.1, 0.9) * w
    ang = uniform(g, 0.0, math.pi)
    c, s = math.cos(ang), math.sin(ang)
    u, v = c * (xx - cx) + s * (yy - cy), c * (yy - cy) - s * (xx - cx)
    info: dict = {"kind": kind, "centre_px": [cy, cx], "angle": ang}
    if kind == "ellipse":
        a, b = uniform(g, 0.08, 0.4) * n, uniform(g, 0.08, 0.4) * n
        rho = torch.sqrt((u / a) ** 2 + (v / b) ** 2)
        sd = (1.0 - rho) * min(a, b)
        info["radii_px"] = [a, b]
    elif kind in ("rect", "bar"):
        if kind == "rect":
            a, b = uniform(g, 0.08, 0.4) * n, uniform(g, 0.08, 0.4) * n
        else:  # a pole or a table edge: long and thin, often crossing the image
            a, b = uniform(g, 0.4, 1.0) * n, uniform(g, 0.02, 0.1) * n
        sd = torch.minimum(a - u.abs(), b - v.abs())
        info["half_sizes_px"] = [a, b]
    elif kind == "polygon":
        k = randint(g, 3, 7)
        r = uniform(g, 0.1, 0.4) * n
        angles = sorted(uniform(g, 0.0, 2 * math.pi) for _ in range(k))
        pts = [(cy + r * math.sin(t), cx + r * math.cos(t)) for t in angles]
        sd = torch.full((h, w), float("inf"))
        for i in range(k):  # convex hull of points on a circle: intersection of half-planes
            (y0, x0), (y1, x1) = pts[i], pts[(i + 1) % k]
            ny, nx = -(x1 - x0), (y1 - y0)  # inward normal for counter-clockwise order
            norm = math.hypot(ny, nx) or 1.0
            d = ((yy - y0) * ny + (xx - x0) * nx) / norm
            sd = torch.minimum(sd, d)
        info["vertices_px"] = [list(p) for p in pts]
    else:  # blob: a low-frequency noise field thresholded, distance from level / gradient
        field_ = fractal((h, w), g, 1, beta=uniform(g, 3.5, 5.0))[0, 0]
        thr = float(torch.quantile(field_.reshape(-1)[::7], uniform(g, 0.5, 0.85)))
        gy, gx = torch.gradient(field_)
        sd = (field_ - thr) / torch.sqrt(gy * gy + gx * gx).clamp_min(1e-4)
        info["threshold"] = thr
    return sd[None, None], info


# ----------------------------------------------------------------------------- illumination
def _draw_mask(g: torch.Generator, camera: Camera, ref_depth_m: float, feature_px: tuple[float, float]
               ) -> tuple[MaskPattern, dict]:
    """A random mask with features of ``feature_px`` pixels at ``ref_depth_m`` (physical units)."""
    m_per_px = camera.pixel_pitch_m * ref_depth_m / camera.sensor_distance_m
    feat = log_uniform(g, *feature_px) * m_per_px
    kind = choice(g, ("bars", "rect", "grating", "dots", "checker", "random"), (0.3, 0.1, 0.2, 0.15, 0.1, 0.15))
    fov = 256 * m_per_px
    beam = uniform(g, 0.5, 1.5) * fov
    if kind == "bars":
        mask = MaskPattern("bars", width_m=feat, height_m=feat * uniform(g, 2.0, 6.0), gap_m=feat * uniform(g, 0.5, 2.0),
                           count=randint(g, 1, 6))
    elif kind == "rect":
        mask = MaskPattern("rect", width_m=feat * uniform(g, 2.0, 8.0), height_m=feat * uniform(g, 2.0, 8.0))
    elif kind == "grating":
        mask = MaskPattern("grating", period_m=2 * feat, duty=uniform(g, 0.3, 0.7), angle_rad=uniform(g, 0, math.pi),
                           beam_m=beam)
    elif kind == "dots":
        pitch = feat * uniform(g, 1.5, 3.0)
        mask = MaskPattern("dots", period_m=pitch, radius_m=pitch * uniform(g, 0.15, 0.4),
                           angle_rad=uniform(g, 0, math.pi / 2), beam_m=beam)
    elif kind == "checker":
        mask = MaskPattern("checker", period_m=2 * feat, angle_rad=uniform(g, 0, math.pi / 2), beam_m=beam)
    else:
        mask = MaskPattern("random", period_m=feat, duty=uniform(g, 0.3, 0.7), angle_rad=uniform(g, 0, math.pi / 2),
                           beam_m=beam, seed=randint(g, 0, 2**31 - 1))
    info = {k: getattr(mask, k) for k in ("kind", "width_m", "height_m", "gap_m", "count", "period_m", "duty",
                                          "radius_m", "angle_rad", "beam_m", "seed")}
    return mask, info


def draw_illumination(g: torch.Generator, cfg: SynthConfig, camera: Camera, size: tuple[int, int]
                      ) -> tuple[CoherentIllumination | ProjectorIllumination | None, dict]:
    """Draw the active source (or ``None``) and its parameters."""
    if not bernoulli(g, cfg.illumination_prob):
        return None, {"illumination": "none"}
    near, far = camera.depth_range_m
    ref = math.sqrt(near * far)
    h, w = size
    if bernoulli(g, cfg.coherent_fraction):
        mask, minfo = _draw_mask(g, camera, ref, cfg.mask_feature_px)
        hy, hx = mask.half_extent_m
        orders = (choice(g, (1, 3, 5)), choice(g, (1, 3, 5)))
        # order spacing at the reference distance: 1.1 to 2 pattern extents
        ty = 2 * hy * uniform(g, 1.1, 2.0) / ref
        tx = 2 * hx * uniform(g, 1.1, 2.0) / ref
        m_per_px = camera.pixel_pitch_m * ref / camera.sensor_distance_m
        offset = (uniform(g, -0.3, 0.3) * h * m_per_px, uniform(g, -0.3, 0.3) * w * m_per_px)
        contrast = uniform(g, 0.1, 0.8) if bernoulli(g, cfg.speckle_prob) else 0.0
        src = CoherentIllumination(mask=mask, orders=orders, order_angle_rad=(math.atan(ty), math.atan(tx)),
                                   order_efficiency=uniform(g, 0.6, 1.0), axis_offset_m=offset,
                                   speckle_contrast=contrast)
        info = {"illumination": "coherent", "mask": minfo, "orders": list(orders),
                "order_angle_rad": list(src.order_angle_rad), "order_efficiency": src.order_efficiency,
                "axis_offset_m": list(offset), "speckle_contrast": contrast}
        return src, info
    # projector: the paper's (56.8 cm, DOF -12.5/+16.5 cm) when inside the range, otherwise a
    # focus inside the range with the same dioptric depth of field
    paper = ProjectorIllumination()
    dn, df = paper.dioptric_half_widths
    if near <= paper.focus_m <= far and bernoulli(g, 0.5):
        focus = paper.focus_m
    else:
        focus = 1.0 / uniform(g, 1.0 / far, 1.0 / near)
    far_limit = 1.0 / (1.0 / focus - df) if 1.0 / focus > df else 1e3
    mask, minfo = _draw_mask(g, camera, focus, cfg.mask_feature_px)
    src = ProjectorIllumination(mask=mask, focus_m=focus, dof_near_m=focus - 1.0 / (1.0 / focus + dn),
                                dof_far_m=far_limit - focus, coc_rad=paper.coc_rad,
                                axis_offset_rad=(uniform(g, -0.02, 0.02), uniform(g, -0.02, 0.02)))
    info = {"illumination": "projector", "mask": minfo, "focus_m": focus, "dof_near_m": src.dof_near_m,
            "dof_far_m": src.dof_far_m, "coc_rad": src.coc_rad, "axis_offset_rad": list(src.axis_offset_rad),
            "speckle_contrast": 0.0}
    return src, info


# ----------------------------------------------------------------------------- scenes
def _texture(g: torch.Generator, size: tuple[int, int], cfg: SynthConfig, textureless: bool
             ) -> tuple[torch.Tensor, dict]:
    if textureless:
        return random_texture(g, size, family="flat")
    return random_texture(g, size, families=cfg.families, spectral_tilt_max=cfg.spectral_tilt)


def make_scene(g: torch.Generator, cfg: SynthConfig, camera: Camera, size: tuple[int, int]) -> Scene:
    """Draw a complete scene (depth, albedo, illumination) from ``g``."""
    h, w = size
    q_lo, q_hi = inverse_depth_range(camera, cfg.depth_margin)
    names = list(cfg.layouts)
    layout = choice(g, names, [cfg.layouts[k] for k in names])
    source, ill = draw_illumination(g, cfg, camera, size)
    textureless = source is not None and bernoulli(g, cfg.textureless_prob)
    params: dict = {"layout": layout, "textureless": textureless}

    if layout == "plane":
        q = depth_plane(h, w, uniform(g, q_lo, q_hi))
    elif layout in ("slanted", "smooth"):
        _, a, b, c = _draw_slant(g, q_lo, q_hi, cfg.slant_spread)
        q = depth_slanted(h, w, a, b, c)
        if layout == "smooth":
            q = depth_smooth(h, w, g, q, uniform(g, 0.05, 0.5) * (q_hi - q_lo))
    else:
        if bernoulli(g, 0.5):
            q = depth_plane(h, w, uniform(g, q_lo, q_hi))
        else:
            _, a, b, c = _draw_slant(g, q_lo, q_hi, cfg.slant_spread)
            q = depth_slanted(h, w, a, b, c)
    q = q.clamp(q_lo, q_hi)
    albedo, tinfo = _texture(g, size, cfg, textureless)
    textures = [tinfo]
    objects = []
    if layout == "layout":
        for _ in range(randint(g, 1, cfg.max_objects)):
            sd, sinfo = region_shape(g, h, w)
            inside = sd > 0
            if not bool(inside.any()):
                continue
            q_behind = det_mean(q[inside])
            if bernoulli(g, 0.8):  # usually in front of what it covers
                q_obj = uniform(g, min(q_behind, q_hi), q_hi)
            else:
                q_obj = uniform(g, q_lo, q_hi)
            if bernoulli(g, 0.3):
                _, a, b, c = _draw_slant(g, q_lo, q_hi, 0.3 * cfg.slant_spread)
                plane = depth_slanted(h, w, a, b, c)
                plane = (plane - det_mean(plane) + q_obj).clamp(q_lo, q_hi)
                sinfo["slanted"] = True
            else:
                plane = depth_plane(h, w, q_obj)
                sinfo["slanted"] = False
            sinfo["inverse_depth"] = q_obj
            q = torch.where(inside, plane, q)
            cover = (sd + 0.5).clamp(0.0, 1.0)
            # the object's bounding box: its own texture is only synthesised there
            rows = (cover[0, 0] > 0).any(1).nonzero()
            cols = (cover[0, 0] > 0).any(0).nonzero()
            y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
            box = (slice(None), slice(None), slice(y0, y1), slice(x0, x1))
            if bernoulli(g, 0.75):
                tex, tinfo = _texture(g, (max(8, y1 - y0), max(8, x1 - x0)), cfg, textureless)
                tex = tex[..., : y1 - y0, : x1 - x0]
                textures.append(tinfo)
            else:  # same material, different shade
                tex = albedo[box] * uniform(g, 0.3, 1.0)
                sinfo["texture"] = "shared"
            patch = albedo[box]
            albedo = albedo.clone()
            albedo[box] = patch + cover[box] * (tex - patch)
            objects.append(sinfo)
    depth = 1.0 / q
    pattern = None
    if source is not None:
        gen = g if isinstance(source, CoherentIllumination) and source.speckle_contrast > 0 else None
        pattern = source.render(camera, depth, generator=gen)
    ambient = log_uniform(g, 0.02, 1.0) if source is not None else 1.0
    radiance = illuminate(albedo, pattern, ambient=ambient, power=1.0)
    params.update({"ambient": ambient, "illumination": ill, "textures": textures, "objects": objects,
                   "inverse_depth_range": [float(q.min()), float(q.max())]})
    return Scene(radiance=radiance, depth=depth, layout=layout, params=params)
