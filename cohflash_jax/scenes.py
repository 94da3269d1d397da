"""Scenes: depth and reflectance over the field of view, and the effects each calls for.

A scene is sampled at continuous image coordinates (u, v) ∈ [0, 1)² (u across columns,
v down rows), so it can be rendered at any size and sub-sampled for mixed pixels or
misregistration without resampling artefacts.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .effects import EffectSettings, parse_effects

Sampler = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

PAPER_DISTANCE_M = 30.5
_CLEAN = ("sidebands", "shot_noise", "dark_current", "read_noise", "quantization", "saturation", "range_falloff")


@dataclasses.dataclass(frozen=True)
class Scene:
    """A named scene: `sample(u, v) → (depth_m, reflectance)` plus the effects it calls for."""

    name: str
    sample: Sampler
    effects: tuple[str, ...] = ()
    description: str = ""
    settings: EffectSettings = dataclasses.field(default_factory=EffectSettings)

    def __post_init__(self):
        object.__setattr__(self, "effects", parse_effects(self.effects))

    def with_effects(self, effects) -> "Scene":
        return dataclasses.replace(self, effects=parse_effects(effects))

    def render(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """Depth (m) and reflectance at pixel centres, float64 (H, W)."""
        v, u = np.meshgrid((np.arange(height) + 0.5) / height, (np.arange(width) + 0.5) / width, indexing="ij")
        return self.sample(u, v)


def _checked(depth, reflectance, name):
    depth = np.asarray(depth, dtype=np.float64)
    reflectance = np.asarray(reflectance, dtype=np.float64)
    if depth.shape != reflectance.shape:
        raise ValueError(f"scene {name!r}: depth {depth.shape} and reflectance {reflectance.shape} differ")
    if not np.all(np.isfinite(depth)) or np.any(depth < 0):
        raise ValueError(f"scene {name!r}: depth must be finite and ≥ 0 m")
    if not np.all(np.isfinite(reflectance)) or np.any(reflectance < 0) or np.any(reflectance > 1):
        raise ValueError(f"scene {name!r}: reflectance must lie in [0, 1]")
    return depth, reflectance


def planar(
    distance_m: float = PAPER_DISTANCE_M,
    reflectance: float = 0.5,
    tilt_m_per_fov: tuple[float, float] = (0.0, 0.0),
    effects=_CLEAN,
) -> Scene:
    """Flat target filling the view (the paper's precision target, Fig. 4a–c)."""
    if not distance_m > 0:
        raise ValueError(f"planar: distance_m must be positive, got {distance_m}")

    def sample(u, v):
        d = distance_m + tilt_m_per_fov[0] * (u - 0.5) + tilt_m_per_fov[1] * (v - 0.5)
        return _checked(d, np.full_like(u, reflectance), "planar")

    return Scene("planar", sample, effects, f"plane at {distance_m} m, reflectance {reflectance}")


def staircase(distance_m: float = PAPER_DISTANCE_M, effects=_CLEAN + ("mixed_pixels",)) -> Scene:
    """The paper's staircase (Fig. 2): 7 steps 0, 5, …, 30 mm proud of a base at `distance_m`,
    in columns across the middle 60 % of the rows, in front of a wall 0.2 m behind."""

    heights_m = 0.005 * np.arange(7)

    def sample(u, v):
        on_stair = (v >= 0.2) & (v < 0.8) & (u >= 0.1) & (u < 0.9)
        step = np.clip(((u - 0.1) / 0.8 * 7).astype(int), 0, 6)
        d = np.where(on_stair, distance_m - heights_m[step], distance_m + 0.2)
        rho = np.where(on_stair, 0.5, 0.3)
        return _checked(d, rho, "staircase")

    return Scene("staircase", sample, effects, "7 steps of 5 mm at 30.5 m before a wall")


def traffic(
    distance_m: float = PAPER_DISTANCE_M, effects=_CLEAN + ("mixed_pixels", "speckle", "background_light")
) -> Scene:
    """A traffic-scene model like Fig. 3: wall, car, pedestrian, light pole, guide board,
    with the illumination shadows they cast on the wall (dark, not absent)."""

    wall = distance_m + 0.6

    def objects(u, v):
        d = np.full_like(u, wall)
        rho = np.full_like(u, 0.3)
        # car: box with a rounded front (depth varies by 3 cm across its width)
        car = (u > 0.08) & (u < 0.45) & (v > 0.55) & (v < 0.85)
        d = np.where(car, distance_m - 0.10 + 0.03 * ((u - 0.265) / 0.185) ** 2, d)
        rho = np.where(car, 0.6, rho)
        # pedestrian: body and head
        body = (u > 0.52) & (u < 0.60) & (v > 0.40) & (v < 0.85)
        head = (u - 0.56) ** 2 / 0.03**2 + (v - 0.34) ** 2 / 0.05**2 < 1
        ped = body | head
        d = np.where(ped, distance_m + 0.1, d)
        rho = np.where(ped, 0.4, rho)
        # light pole and its lamp arm
        pole = ((u > 0.70) & (u < 0.725) & (v > 0.10)) | ((u > 0.62) & (u < 0.725) & (v > 0.10) & (v < 0.13))
        d = np.where(pole, distance_m - 0.25, d)
        rho = np.where(pole, 0.7, rho)
        # guide board on a post
        board = (u > 0.80) & (u < 0.95) & (v > 0.20) & (v < 0.40)
        post = (u > 0.865) & (u < 0.885) & (v >= 0.40)
        d = np.where(board | post, distance_m - 0.35, d)
        rho = np.where(board, 0.8, np.where(post, 0.5, rho))
        return d, rho, d < wall - 1e-9

    def sample(u, v):
        d, rho, occupied = objects(u, v)
        # shadows: the illuminator sits beside the receiver, so each object darkens the
        # wall a little to its right and below
        _, _, shadowing = objects(u - 0.015, v - 0.02)
        shadow = shadowing & ~occupied
        rho = np.where(shadow, 0.03, rho)
        return _checked(d, rho, "traffic")

    return Scene("traffic", sample, effects, "traffic model: car, pedestrian, pole, board, wall, shadows")


def from_arrays(depth_m, reflectance=None, name: str = "arrays", effects=_CLEAN) -> Scene:
    """Scene from a depth map (m) and optional reflectance map of any resolution; both are
    sampled nearest-neighbour at the requested sensor coordinates."""
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.ndim != 2 or min(depth.shape) < 1:
        raise ValueError(f"depth map must be 2-D, got shape {depth.shape}")
    rho = np.full_like(depth, 0.5) if reflectance is None else np.asarray(reflectance, dtype=np.float64)
    depth, rho = _checked(depth, rho, name)
    rows, cols = depth.shape

    def sample(u, v):
        r = np.clip((np.asarray(v) * rows).astype(int), 0, rows - 1)
        c = np.clip((np.asarray(u) * cols).astype(int), 0, cols - 1)
        return depth[r, c], rho[r, c]

    return Scene(name, sample, effects, f"user arrays {rows}×{cols}")


def _load_map(path: Path) -> tuple[np.ndarray, float]:
    """A 2-D map from `.npy` or an image → (float64 values, the full scale of the file's dtype:
    255 for 8-bit and 65535 for 16-bit images, 1 otherwise)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene map not found: {path}")
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise ValueError(f"{path}: not a readable .npy array ({exc})") from None
    else:
        from .fileio import read_gray_image

        arr = read_gray_image(path)
        if arr is None:
            raise ValueError(f"could not read image {path} (not an image OpenCV can decode)")
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise ValueError(f"{path}: a map must hold real numbers, got dtype {arr.dtype}")
    full_scale = (
        float(np.iinfo(arr.dtype).max)
        if np.issubdtype(arr.dtype, np.integer) and path.suffix.lower() != ".npy"
        else 1.0
    )
    return arr.astype(np.float64), full_scale


def from_files(
    depth_path,
    reflectance_path=None,
    depth_scale_m: float = 1.0,
    reflectance_scale: float | None = None,
    effects=_CLEAN,
) -> Scene:
    """Scene from files: `.npy` arrays (metres and [0, 1]) or images (e.g. 16-bit PNG).

    Image values are multiplied by `depth_scale_m` (e.g. 0.001 for depth in mm) and by
    `reflectance_scale` (default 1/full scale of the image's dtype: 1/255 for 8-bit, 1/65535
    for 16-bit)."""
    depth = _load_map(depth_path)[0] * depth_scale_m
    rho = None
    if reflectance_path is not None:
        rho, full_scale = _load_map(reflectance_path)
        if reflectance_scale is None:
            reflectance_scale = 1.0 / full_scale
        rho = rho * reflectance_scale
    return from_arrays(depth, rho, name=Path(depth_path).stem, effects=effects)


BUILTIN_SCENES: dict[str, Callable[[], Scene]] = {
    "planar": planar,
    "staircase": staircase,
    "traffic": traffic,
}


def get_scene(name: str) -> Scene:
    try:
        return BUILTIN_SCENES[name]()
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; built-in scenes: {', '.join(BUILTIN_SCENES)}") from None
