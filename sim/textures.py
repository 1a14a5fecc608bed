"""Procedural textures for the simulated wreck: rusty plating, deck, sand.

Pure math (numpy and cv2 resizing, no I/O). Every texture is unique (no tiling) and
multi-scale, from metre-sized rust and growth patches down to centimetre speckle, so that
corner detectors (KLT, SIFT) find plenty of stable, distinctive features at any range
from 0.5 m to several metres. All randomness comes from the `numpy.random.Generator`
passed in, so a seed gives the same bytes on every machine.

Textures are (rows, cols, 3) uint8 RGB albedo images; texel size is chosen by the caller
(metres per texel). Row 0 is the top (highest z for vertical faces), so streaks run down.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

FloatImage = npt.NDArray[np.float32]
ByteImage = npt.NDArray[np.uint8]


def value_noise(
    rng: np.random.Generator, shape: tuple[int, int], cell_texels: float, *, stretch_v: float = 1.0
) -> FloatImage:
    """Smooth random field in [-1, 1] of `shape` whose features are `cell_texels` wide.

    A coarse grid of random values resized with bicubic interpolation; `stretch_v` > 1
    elongates features along the rows' axis (vertical streaks).
    """
    rows, cols = shape
    cell_u = max(cell_texels, 1.0)
    cell_v = max(cell_texels * stretch_v, 1.0)
    grid_cols = int(np.ceil(cols / cell_u)) + 3
    grid_rows = int(np.ceil(rows / cell_v)) + 3
    grid = rng.uniform(-1.0, 1.0, size=(grid_rows, grid_cols)).astype(np.float32)
    big = cv2.resize(
        grid,
        (round(grid_cols * cell_u), round(grid_rows * cell_v)),
        interpolation=cv2.INTER_CUBIC,
    )
    # Skip the first cell on each side: bicubic resizing is distorted at the border.
    top, left = int(np.ceil(cell_v)), int(np.ceil(cell_u))
    return np.ascontiguousarray(big[top : top + rows, left : left + cols])


def fractal_noise(
    rng: np.random.Generator,
    shape: tuple[int, int],
    largest_texels: float,
    smallest_texels: float,
    *,
    persistence: float = 0.6,
    stretch_v: float = 1.0,
) -> FloatImage:
    """Sum of value-noise octaves (halving feature size) normalised to about [-1, 1].

    Built as a pyramid: random values on the coarsest grid, then at each octave the sum so
    far is upsampled twofold (bicubic) and the next octave's random grid added, so the cost
    is about that of the finest grid rather than one full-size resize per octave.
    """
    rows, cols = shape
    octaves = max(
        int(np.floor(np.log2(max(largest_texels, 1.0) / max(smallest_texels, 1.0)))) + 1, 1
    )
    finest_u = max(smallest_texels, 1.0)
    finest_v = max(smallest_texels * stretch_v, 1.0)
    coarse_u = finest_u * 2 ** (octaves - 1)
    coarse_v = finest_v * 2 ** (octaves - 1)
    grid_rows = int(np.ceil(rows / coarse_v)) + 3
    grid_cols = int(np.ceil(cols / coarse_u)) + 3
    total = rng.uniform(-1.0, 1.0, size=(grid_rows, grid_cols)).astype(np.float32)
    amplitude = 1.0
    weight = 1.0
    for _ in range(octaves - 1):
        grid_rows, grid_cols = 2 * grid_rows, 2 * grid_cols
        total = np.asarray(
            cv2.resize(total, (grid_cols, grid_rows), interpolation=cv2.INTER_CUBIC), np.float32
        )
        amplitude *= persistence
        weight += amplitude
        total += amplitude * rng.uniform(-1.0, 1.0, size=(grid_rows, grid_cols)).astype(np.float32)
    full = cv2.resize(
        total,
        (round(grid_cols * finest_u), round(grid_rows * finest_v)),
        interpolation=cv2.INTER_CUBIC,
    )
    # Skip the first cell on each side: bicubic resizing is distorted at the border.
    top, left = int(np.ceil(finest_v)), int(np.ceil(finest_u))
    out = np.asarray(full[top : top + rows, left : left + cols], dtype=np.float32)
    return np.ascontiguousarray(_fit(out, shape)) * np.float32(1.6 / weight)


def _fit(image: FloatImage, shape: tuple[int, int]) -> FloatImage:
    rows, cols = shape
    if image.shape[0] >= rows and image.shape[1] >= cols:
        return image[:rows, :cols]
    out = np.zeros(shape, dtype=np.float32)
    out[: image.shape[0], : image.shape[1]] = image[:rows, :cols]
    return out


def _speckle(rng: np.random.Generator, shape: tuple[int, int], density: float) -> FloatImage:
    """Sparse random dots (barnacles, shells): 1 at a fraction `density` of texels, blurred."""
    dots = (rng.random(shape, dtype=np.float32) < density).astype(np.float32)
    return cv2.GaussianBlur(dots, (3, 3), 0.8) * 2.0


def _flakes(
    rng: np.random.Generator, shape: tuple[int, int], largest_texels: float, coverage: float
) -> FloatImage:
    """Crisp-edged blotches (paint flakes, pits, pebbles) covering about `coverage` of the
    area: thresholded fractal noise with a 1-2 texel soft edge, corners at every scale."""
    noise = fractal_noise(rng, shape, largest_texels, 1.0, persistence=0.75)
    threshold = np.float32(np.quantile(noise[::7, ::7], 1.0 - coverage))
    flakes: FloatImage = np.clip((noise - threshold) * np.float32(8.0) + np.float32(0.5), 0.0, 1.0)
    return flakes


def _mix(base: FloatImage, color: tuple[float, float, float], weight: FloatImage) -> None:
    """In place: base = base * (1 - w) + color * w, per pixel weight w in [0, 1]."""
    w = np.clip(weight, 0.0, 1.0)
    for c in range(3):
        channel = base[..., c]
        channel -= (channel - np.float32(color[c])) * w


def _to_bytes(rgb: FloatImage) -> ByteImage:
    out: ByteImage = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return out


def plating_texture(
    rng: np.random.Generator, shape: tuple[int, int], texel_m: float, *, vertical: bool
) -> ByteImage:
    """Riveted steel plating with rust, streaks and marine growth.

    Plate seams on a staggered grid (strakes about 1 m high, plates 1.5-3 m long), rivet
    rows along the seams, rust streaks running down (vertical faces), encrusting growth
    patches and barnacle speckle.
    """
    rows, cols = shape
    per_m = 1.0 / texel_m
    rgb = np.empty((rows, cols, 3), dtype=np.float32)
    rgb[:] = (0.42, 0.36, 0.30)  # weathered steel
    big = fractal_noise(rng, shape, 3.0 * per_m, 0.02 * per_m)
    rgb *= (1.0 + 0.35 * big)[..., None]
    rust = fractal_noise(rng, shape, 1.5 * per_m, 0.01 * per_m, persistence=0.7)
    _mix(rgb, (0.55, 0.27, 0.12), (rust - 0.1) * 1.5)
    if vertical:
        streak = fractal_noise(rng, shape, 0.4 * per_m, 0.03 * per_m, stretch_v=8.0)
        _mix(rgb, (0.32, 0.16, 0.08), (streak - 0.25) * 1.2)
    # Plate seams and rivets: strakes of random height, butts staggered per strake.
    seam = np.zeros(shape, dtype=np.float32)
    rivet = np.zeros(shape, dtype=np.float32)
    seam_w = max(round(0.012 * per_m), 1)
    pitch = max(round(0.075 * per_m), 2)
    r = 0
    while r < rows:
        strake = int(rng.uniform(0.8, 1.3) * per_m)
        seam[r : r + seam_w] = 1.0
        rivet[r + 2 * seam_w : r + 2 * seam_w + seam_w, ::pitch] = 1.0
        c = int(rng.uniform(0.0, 2.0) * per_m)
        while c < cols:
            seam[r : r + strake, c : c + seam_w] = 1.0
            rivet[r : r + strake : pitch, c + 2 * seam_w : c + 3 * seam_w] = 1.0
            c += int(rng.uniform(1.5, 3.0) * per_m)
        r += strake
    seam = np.asarray(cv2.GaussianBlur(seam, (0, 0), max(seam_w * 0.5, 0.5)), np.float32)
    rgb *= (1.0 - 0.55 * np.clip(seam, 0, 1))[..., None]
    rivet = cv2.GaussianBlur(rivet, (0, 0), max(seam_w * 0.6, 0.5)) * 1.5
    _mix(rgb, (0.70, 0.58, 0.45), rivet)
    growth = fractal_noise(rng, shape, 2.0 * per_m, 0.01 * per_m, persistence=0.65)
    _mix(rgb, (0.36, 0.44, 0.30), (growth - 0.35) * 2.5)
    _mix(rgb, (0.22, 0.15, 0.10), _flakes(rng, shape, 0.25 * per_m, 0.18))
    _mix(rgb, (0.66, 0.52, 0.38), _flakes(rng, shape, 0.08 * per_m, 0.10))
    _mix(rgb, (0.85, 0.82, 0.74), _speckle(rng, shape, 0.006))
    fine = fractal_noise(rng, shape, 0.05 * per_m, 1.0, persistence=0.8)
    rgb *= (1.0 + 0.3 * fine)[..., None]
    return _to_bytes(rgb)


def deck_texture(rng: np.random.Generator, shape: tuple[int, int], texel_m: float) -> ByteImage:
    """Deck: rotten planks along the columns' axis, silt, growth and debris speckle."""
    rows, cols = shape
    per_m = 1.0 / texel_m
    rgb = np.empty((rows, cols, 3), dtype=np.float32)
    rgb[:] = (0.40, 0.34, 0.26)
    grain = fractal_noise(rng, shape, 0.6 * per_m, 0.01 * per_m, stretch_v=0.15)
    rgb *= (1.0 + 0.3 * grain)[..., None]
    plank = np.zeros(shape, dtype=np.float32)
    width = max(int(0.18 * per_m), 2)
    gap = max(round(0.01 * per_m), 1)
    for r in range(0, rows, width):
        plank[r : r + gap] = 1.0
        c = int(rng.uniform(0, 4.0) * per_m)
        while c < cols:
            plank[r : r + width, c : c + gap] = 1.0
            c += int(rng.uniform(2.0, 5.0) * per_m)
    rgb *= (1.0 - 0.5 * cv2.GaussianBlur(plank, (0, 0), max(gap * 0.6, 0.5)))[..., None]
    silt = fractal_noise(rng, shape, 2.5 * per_m, 0.02 * per_m)
    _mix(rgb, (0.62, 0.58, 0.48), (silt - 0.1) * 1.2)
    growth = fractal_noise(rng, shape, 1.0 * per_m, 0.01 * per_m, persistence=0.7)
    _mix(rgb, (0.30, 0.42, 0.28), (growth - 0.3) * 2.5)
    _mix(rgb, (0.20, 0.17, 0.13), _flakes(rng, shape, 0.3 * per_m, 0.12))
    _mix(rgb, (0.88, 0.85, 0.78), _speckle(rng, shape, 0.005))
    fine = fractal_noise(rng, shape, 0.05 * per_m, 1.0, persistence=0.8)
    rgb *= (1.0 + 0.3 * fine)[..., None]
    return _to_bytes(rgb)


def sand_texture(rng: np.random.Generator, shape: tuple[int, int], texel_m: float) -> ByteImage:
    """Seafloor sand: wave ripples (about 10 cm wavelength, wandering crests), dark patches,
    shells and pebbles."""
    rows, cols = shape
    per_m = 1.0 / texel_m
    rgb = np.empty((rows, cols, 3), dtype=np.float32)
    rgb[:] = (0.66, 0.60, 0.47)
    yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float32)
    wander = fractal_noise(rng, shape, 3.0 * per_m, 0.2 * per_m)
    wavelength = 0.11 * per_m
    phase = (xx * 0.94 + yy * 0.34) / wavelength * 2.0 * np.pi + 6.0 * wander
    ripple = np.sin(phase) + 0.3 * np.sin(2.0 * phase)
    strength = 0.5 + 0.5 * fractal_noise(rng, shape, 4.0 * per_m, 0.5 * per_m)
    rgb *= (1.0 + 0.16 * ripple * strength)[..., None]
    patches = fractal_noise(rng, shape, 5.0 * per_m, 0.05 * per_m)
    _mix(rgb, (0.38, 0.36, 0.30), (patches - 0.2) * 1.5)
    _mix(rgb, (0.30, 0.27, 0.22), _flakes(rng, shape, 0.4 * per_m, 0.06))
    _mix(rgb, (0.90, 0.88, 0.82), _speckle(rng, shape, 0.008))
    _mix(rgb, (0.25, 0.22, 0.20), _speckle(rng, shape, 0.005))
    fine = fractal_noise(rng, shape, 0.04 * per_m, 1.0, persistence=0.8)
    rgb *= (1.0 + 0.25 * fine)[..., None]
    return _to_bytes(rgb)
