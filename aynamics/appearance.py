"""The randomised appearance of a rendered scene: lights, object textures, floor and sky, drawn from a seed.

As in the paper: 1-3 directional lights (direction, intensity, shadows), object textures (checkerboard, gradient or
plain colours) and natural photographs on the floor and in the sky, so that optical flow has texture to follow. The
photographs come from `textures_dir` (any .png/.jpg) or, by default, scikit-image's bundled sample images; nothing is
downloaded. `aynamics.render` puts an `Appearance` on the scene's MuJoCo model (`render_model`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aynamics.scene import MAX_OBJECTS
from aynamics.video_io import IMAGE_SUFFIXES, image_files

# scikit-image sample photographs shipped inside the wheel (no download): natural textures for floor and sky
DEFAULT_IMAGES = (
    "brick.png",
    "grass.png",
    "gravel.png",
    "rocket.jpg",
    "coffee.png",
    "chelsea.png",
    "astronaut.png",
    "motorcycle_left.png",
    "color.png",
    "hubble_deep_field.jpg",
)


@dataclass(frozen=True)
class Light:
    """A directional light: unit direction it shines along (world), diffuse intensity, shadow casting."""

    direction: tuple[float, float, float]
    diffuse: float
    castshadow: bool


@dataclass(frozen=True)
class ObjectLook:
    """Texture of one object: 'checker' (2×2 per face), 'gradient' or 'plain'; colours rgb in [0, 1]."""

    kind: str
    rgb1: tuple[float, float, float]
    rgb2: tuple[float, float, float]


@dataclass(frozen=True)
class Appearance:
    """Everything randomised about how a scene looks; `sample_appearance(seed)` draws one."""

    lights: tuple[Light, ...]
    ambient: float
    objects: tuple[ObjectLook, ...]  # object i wears objects[i % len(objects)]
    floor_image: Path | None  # None: a plain floor of colour floor_rgb (backdrop "plain")
    sky_image: Path | None
    floor_repeat: float  # photograph repeats per metre of floor
    floor_rgb: tuple[float, float, float] = (0.5, 0.5, 0.5)
    sky_rgb: tuple[float, float, float] = (0.6, 0.6, 0.6)


def default_texture_dir() -> Path:
    """Folder of scikit-image's bundled sample photographs (part of the installed wheel)."""
    import skimage.data

    return Path(skimage.data.__file__).parent


def texture_images(textures_dir: str | Path | None = None) -> list[Path]:
    """The photographs to draw floor and sky textures from: every image in `textures_dir`, or the default set.

    Raises:
        FileNotFoundError: `textures_dir` does not exist.
        ValueError: it holds no .png/.jpg/.jpeg/.bmp image.
    """
    if textures_dir is None:
        root = default_texture_dir()
        paths = [root / name for name in DEFAULT_IMAGES if (root / name).is_file()]
        if not paths:
            raise ValueError(f"no default textures found in {root}; pass textures_dir")
        return paths
    root = Path(textures_dir)
    if not root.is_dir():
        raise FileNotFoundError(2, f"textures_dir {str(root)!r} is not a folder", str(root))
    paths = image_files(root, IMAGE_SUFFIXES)
    if not paths:
        raise ValueError(f"textures_dir {str(root)!r}: no images ({', '.join(IMAGE_SUFFIXES)}) in it")
    return paths


BACKDROPS = ("photos", "plain")


def sample_appearance(
    seed: int, textures_dir: str | Path | None = None, n_objects: int = MAX_OBJECTS, backdrop: str = "photos"
) -> Appearance:
    """Draw lighting, object textures and the floor/sky from `seed` (same seed, same look).

    backdrop: "photos" (floor and sky photographs, the default) or "plain" (one random colour each: an easier,
    texture-free look, e.g. for a small model trained from scratch).
    """
    if backdrop not in BACKDROPS:
        raise ValueError(f"backdrop = {backdrop!r}: must be one of {BACKDROPS}")
    rng = np.random.default_rng(seed)
    images = texture_images(textures_dir) if backdrop == "photos" else []
    lights = []
    n_lights = int(rng.integers(1, 4))
    for k in range(n_lights):
        elevation = np.radians(rng.uniform(35, 85))  # angle above the horizon
        azimuth = rng.uniform(0, 2 * np.pi)
        direction = -np.array(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
        )
        diffuse = float(rng.uniform(0.4, 0.9) / np.sqrt(n_lights))
        lights.append(Light(tuple(float(x) for x in direction), diffuse, bool(k == 0 or rng.random() < 0.3)))
    looks = []
    for _ in range(n_objects):
        kind = str(rng.choice(["checker", "gradient", "plain"]))
        rgb1 = tuple(float(x) for x in rng.uniform(0.05, 1.0, 3))
        rgb2 = tuple(float(x) for x in rng.uniform(0.05, 1.0, 3))
        looks.append(ObjectLook(kind, rgb1, rgb2))
    if backdrop == "plain":
        floor_rgb = tuple(float(x) for x in rng.uniform(0.25, 0.75, 3))
        backdrop_look = {"floor_rgb": floor_rgb, "sky_rgb": tuple(float(x) for x in rng.uniform(0.4, 0.9, 3))}
        backdrop_look |= {"floor_image": None, "sky_image": None}
    else:
        floor, sky = rng.choice(len(images), size=2, replace=len(images) < 2)
        backdrop_look = {"floor_image": images[int(floor)], "sky_image": images[int(sky)]}
    ambient = float(rng.uniform(0.15, 0.35))
    floor_repeat = float(rng.uniform(0.2, 0.6)) if backdrop == "photos" else 1.0  # a flat floor has no repeat
    return Appearance(
        lights=tuple(lights), ambient=ambient, objects=tuple(looks), floor_repeat=floor_repeat, **backdrop_look
    )
