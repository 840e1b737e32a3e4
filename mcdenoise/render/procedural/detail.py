"""Fine surface detail: what real scenes' surfaces have and the procedural textures lack (issue 19).

The ``detailed`` world is the ``rich`` world plus this pass. Real interiors and products are
covered in high-contrast, high-frequency patterns: tiled floors and walls with thin grout lines,
brick, printed text, woven fabric, terrazzo and granite speckle, fine wood grain, cobbles. At a few
pixels per period these are what a denoiser must keep (the albedo guide carries them, blurred by
depth of field and noisy where it is) and where kernels trained on smooth procedural colour
smear. The classic textures are 32-128 texels of smooth noise, stripes and cells.

What the pass does, from a random stream of its own (classic and rich draws stay bit-identical):

* replaces the colour texture of many BSDFs (walls, floors, furniture, objects) by one of
  :data:`DETAIL_KINDS`, 128-256 texels, repeated by a random UV scale;
* makes the roughness of half of the principled materials it details vary with the same pattern
  (polished tiles in rough grout, or the reverse), since glossiness that changes per pixel is what
  a specular kernel must not average away (conductors have no colour parameter and are left as
  drawn);
* adds a bump map that follows the pattern to some (grout and mortar recessed, fabric threads).

Every image is tileable, float32, and its reflectances lie in [0.02, 0.92].
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from mcdenoise.render.procedural import textures as pt
from mcdenoise.render.procedural.materials import _bitmap
from mcdenoise.render.procedural.seeds import _loguniform
from mcdenoise.render.procedural.transforms import _rotate, _scale, _xform

__all__ = ["DETAIL_KINDS", "detail_texture", "Detailer"]

LO, HI = 0.02, 0.92
#: colour parameters of the BSDFs the generator makes.
_COLOUR_KEYS = ("reflectance", "diffuse_reflectance", "base_color")


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel-centre coordinates (size, size) in [0, 1): y, x."""
    y, x = np.mgrid[0:size, 0:size]
    return (y + 0.5) / size, (x + 0.5) / size


def _palette(rng: np.random.Generator, n: int, contrast: float) -> np.ndarray:
    """``n`` related colours (n, 3): a base hue, values spread by ``contrast`` in log space."""
    # Mostly muted colours over a wide range of values (dark wood, white tile), as real materials.
    hue = rng.uniform(0.0, 1.0, 3)
    sat = rng.uniform(0.0, 0.9) ** 1.5
    base = _loguniform(rng, 0.05, 0.8) * ((1 - sat) + sat * hue / max(hue.max(), 1e-6))
    cols = base[None] * np.exp(rng.normal(0, contrast, (n, 1))) * np.exp(rng.normal(0, 0.15, (n, 3)))
    return np.clip(cols, LO, HI)


def tiles(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Rectangular tiles or bricks (rows offset by half a tile) with thin grout lines; per-tile colour.

    Returns (rgb (size, size, 3), height (size, size) in [0, 1]: grout 0, tiles 1)."""
    nx = int(rng.integers(2, 17))
    ny = int(nx * rng.choice([1, 1, 2, 3])) if rng.random() < 0.5 else nx
    stagger = rng.random() < 0.4
    y, x = _grid(size)
    row = np.floor(y * ny)
    xs = x * nx + (0.5 * (row % 2) if stagger else 0.0)
    col = np.floor(xs) % nx
    fx, fy = xs - np.floor(xs), y * ny - row
    grout = rng.uniform(0.02, 0.08)
    # Grout of equal width in texels along both axes.
    gx, gy = grout, grout * ny / nx
    edge = np.minimum(np.minimum(fx, 1 - fx) / gx, np.minimum(fy, 1 - fy) / gy)
    mortar = np.clip(edge - 0.5, 0, 1)  # 0 in the grout, 1 on the tile, one-texel ramp
    pal = _palette(rng, int(rng.integers(1, 5)), rng.uniform(0.05, 0.6))
    idx = (rng.permutation(nx * ny * 2)[(row * nx + col).astype(int) % (nx * ny * 2)]) % len(pal)
    tile = pal[idx] * (1 + 0.15 * (pt.tileable_noise(rng, size, 1.5)[..., None] - 0.5))
    g = rng.uniform(0.03, 0.8)
    grout_c = np.clip(np.array([g, g, g]) * rng.uniform(0.85, 1.15, 3), LO, HI)
    rgb = tile * mortar[..., None] + grout_c * (1 - mortar[..., None])
    return np.clip(rgb, LO, HI), mortar


def glyphs(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Lines of random glyphs, dark ink on light paper (print, labels, book spines)."""
    gw, gh = int(rng.integers(3, 6)), int(rng.integers(5, 8))  # glyph bitmap cells
    cell = int(rng.choice([1, 1, 2]))  # texels per bitmap cell
    line = gh * cell + int(rng.integers(cell, 4 * cell + 1))  # line pitch, texels
    adv = gw * cell + cell  # glyph advance
    n_glyphs = 40
    bank = rng.random((n_glyphs, gh, gw)) < rng.uniform(0.3, 0.55)
    ink = np.zeros((size, size), bool)
    for y0 in range(0, size - gh * cell + 1, line):
        x0 = 0
        while x0 + gw * cell <= size:
            if rng.random() < 0.15:  # a space between words
                x0 += adv
                continue
            g = bank[int(rng.integers(n_glyphs))]
            ink[y0:y0 + gh * cell, x0:x0 + gw * cell] = np.kron(g, np.ones((cell, cell), bool))
            x0 += adv
    paper = np.clip(rng.uniform(0.55, 0.9) * rng.uniform(0.9, 1.0, 3), LO, HI)
    ink_c = rng.uniform(0.02, 0.08, 3) if rng.random() < 0.7 else _palette(rng, 1, 0.3)[0] * 0.4
    if rng.random() < 0.3:  # light print on a dark ground
        paper, ink_c = np.clip(ink_c * 1.5, LO, HI), paper
    rgb = np.where(ink[..., None], ink_c, paper)
    return np.clip(rgb, LO, HI).astype(np.float64), 1.0 - ink


def weave(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Plain or twill fabric: warp and weft threads a few texels wide, over and under."""
    period = int(rng.choice([4, 4, 8, 8, 16]))
    y, x = np.mgrid[0:size, 0:size]
    cx, cy = x // period, y // period
    twill = rng.random() < 0.4
    over = ((cx + cy) % 2 == 0) if not twill else (((cx - cy) % 3) == 0)
    ux, uy = (x % period + 0.5) / period, (y % period + 0.5) / period
    warp_h = np.sin(np.pi * ux) ** 0.5  # a thread's rounded profile
    weft_h = np.sin(np.pi * uy) ** 0.5
    h = np.where(over, warp_h, weft_h)
    pal = _palette(rng, 2, rng.uniform(0.1, 0.8))
    rgb = np.where(over[..., None], pal[0], pal[1]) * (0.55 + 0.45 * h[..., None])
    return np.clip(rgb, LO, HI), h


def speckle(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Terrazzo or granite: chips of a few texels in 2-4 colours scattered over a ground."""
    pal = _palette(rng, int(rng.integers(3, 6)), rng.uniform(0.3, 1.0))
    rgb = np.broadcast_to(pal[0], (size, size, 3)).copy()
    h = np.zeros((size, size))
    n = int(size * size * rng.uniform(0.004, 0.03))
    r_hi = rng.uniform(1.0, 4.0)
    for _ in range(n):
        cx, cy = rng.uniform(0, size, 2)
        r = rng.uniform(0.6, r_hi)
        # Only the texels within r of the centre, indices wrapped around: tileable, and cheap.
        ys = np.arange(int(np.floor(cy - r)), int(np.ceil(cy + r)) + 1)
        xs = np.arange(int(np.floor(cx - r)), int(np.ceil(cx + r)) + 1)
        m = ((ys[:, None] + 0.0 - cy) ** 2 + (xs[None, :] + 0.0 - cx) ** 2) < r * r
        yy, xx = np.ix_(ys % size, xs % size)
        c = pal[1 + int(rng.integers(len(pal) - 1))]
        rgb[yy, xx] = np.where(m[..., None], c, rgb[yy, xx])
        h[yy, xx] = np.where(m, 1.0, h[yy, xx])
    return np.clip(rgb, LO, HI), h


def grain(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Fine wood grain: many thin growth lines, warped by noise; planks with dark seams."""
    k = int(rng.integers(12, 48))
    y, x = _grid(size)
    warp = pt.tileable_noise(rng, size, rng.uniform(2.0, 3.0)) * rng.uniform(0.5, 3.0)
    t = np.mod(k * y + warp, 1.0)
    lines = np.exp(-((t - 0.5) / rng.uniform(0.05, 0.2)) ** 2)
    planks = int(rng.integers(1, 9))
    seam = np.minimum(np.mod(x * planks, 1.0), 1 - np.mod(x * planks, 1.0)) * size / planks > 1.0
    pal = _palette(rng, 2, rng.uniform(0.2, 0.6))
    rgb = pal[0] * (1 - lines[..., None]) + pal[1] * lines[..., None]
    rgb = rgb * np.where(seam, 1.0, rng.uniform(0.2, 0.5))[..., None]
    return np.clip(rgb, LO, HI), seam * (1 - 0.3 * lines)


def cobbles(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Stones or scales: Worley cells with dark joints of one or two texels, a colour per cell."""
    n = int(rng.integers(16, 200))
    pts = rng.random((n, 2)) * size
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    d1 = np.full((size, size), np.inf)
    d2 = np.full((size, size), np.inf)
    owner = np.zeros((size, size), int)
    second = np.zeros((size, size), int)
    for i, (px, py) in enumerate(pts):
        dx = np.abs(x - px)
        dy = np.abs(y - py)
        d = np.hypot(np.minimum(dx, size - dx), np.minimum(dy, size - dy))
        closer = d < d1
        nearer2 = ~closer & (d < d2)
        d2 = np.where(closer, d1, np.where(nearer2, d, d2))
        second = np.where(closer, owner, np.where(nearer2, i, second))
        owner = np.where(closer, i, owner)
        d1 = np.minimum(d1, d)
    # Distance to the joint (the bisector of the two nearest points), in texels.
    sep = pts[owner] - pts[second]
    sep = np.hypot(*[np.minimum(np.abs(c), size - np.abs(c)) for c in sep.transpose(2, 0, 1)])
    edge = (d2 ** 2 - d1 ** 2) / (2 * np.maximum(sep, 1e-6))
    joint = np.clip(edge / rng.uniform(0.5, 1.5) - 0.5, 0, 1)
    pal = _palette(rng, int(rng.integers(2, 6)), rng.uniform(0.1, 0.5))
    cell = pal[owner % len(pal)] * (0.8 + 0.4 * rng.random(n)[owner][..., None])
    dark = rng.uniform(0.02, 0.2)
    rgb = cell * joint[..., None] + dark * (1 - joint[..., None])
    return np.clip(rgb, LO, HI), joint


#: detail kind -> (function, weight).
DETAIL_KINDS: dict[str, tuple[Callable[[np.random.Generator, int], tuple[np.ndarray, np.ndarray]], float]] = {
    "tiles": (tiles, 0.25),
    "glyphs": (glyphs, 0.12),
    "weave": (weave, 0.15),
    "speckle": (speckle, 0.15),
    "grain": (grain, 0.18),
    "cobbles": (cobbles, 0.15),
}


def detail_texture(rng: np.random.Generator, kind: str, size: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """One detail texture: (rgb (size, size, 3) float32 in [LO, HI], height (size, size) float32 in [0, 1])."""
    if kind not in DETAIL_KINDS:
        raise ValueError(f"unknown detail texture {kind!r}; kinds: {', '.join(DETAIL_KINDS)}")
    rgb, h = DETAIL_KINDS[kind][0](rng, size)
    return np.clip(rgb, LO, HI).astype(np.float32), np.clip(h, 0, 1).astype(np.float32)


def _uv(rng: np.random.Generator, lo: float, hi: float) -> Any:
    uv = _loguniform(rng, lo, hi)
    return _xform(_rotate([0, 0, 1], float(rng.choice([0.0, np.pi / 2, rng.uniform(0, 2 * np.pi)])))
                  @ _scale([uv, uv * rng.uniform(0.8, 1.25), 1.0]))


class Detailer:
    """Puts fine detail on BSDF dicts, each once, from its own random stream.

    Procedural meshes load their BSDF when they are built, so the scene builder calls this on
    their dicts first (:attr:`~mcdenoise.render.procedural.objects._Builder.detail`);
    :meth:`finish` then treats the dict BSDFs left in the scene. ``added`` counts what was put on.
    """

    def __init__(self, rng: np.random.Generator, *, p_colour: float = 0.55) -> None:
        self.rng, self.p_colour = rng, p_colour
        self.added: dict[str, int] = {}
        # id -> the dict itself: holding every seen dict keeps its id() from being reused.
        self._seen: dict[int, dict] = {}
        self._kinds = list(DETAIL_KINDS)
        w = np.array([DETAIL_KINDS[k][1] for k in self._kinds])
        self._p = w / w.sum()

    def _count(self, what: str) -> None:
        self.added[what] = self.added.get(what, 0) + 1

    def __call__(self, bsdf: dict) -> None:
        """Detail on one BSDF dict (in place; a bump map's nested BSDF gets it), once per dict."""
        while bsdf.get("type") == "bumpmap" and isinstance(bsdf.get("nested"), dict):
            bsdf = bsdf["nested"]
        if id(bsdf) in self._seen:
            return
        self._seen[id(bsdf)] = bsdf
        rng = self.rng
        key = next((k for k in _COLOUR_KEYS if k in bsdf), None)
        if key is None or rng.random() >= self.p_colour:
            return
        kind = self._kinds[int(rng.choice(len(self._kinds), p=self._p))]
        rgb, h = detail_texture(rng, kind, int(rng.choice([128, 256])))
        to_uv = _uv(rng, 0.7, 8.0)
        bsdf[key] = {"type": "bitmap", "bitmap": _bitmap(rgb), "to_uv": to_uv, "raw": True, "filter_type": "bilinear"}
        self._count(kind)
        # Only principled BSDFs have both a colour and a roughness texture slot here (the metals
        # carry no colour parameter, so they never reach this point).
        rough_key = {"principled": "roughness"}.get(bsdf["type"])
        if rough_key and rng.random() < 0.5:
            a, b = sorted(_loguniform(rng, 0.02, 0.7) for _ in range(2))
            t = h if rng.random() < 0.5 else 1 - h  # tiles glossy and grout rough, or the reverse
            rough = (a + (b - a) * t)[..., None]
            if bsdf["type"] == "principled":
                rough = np.sqrt(rough)  # principled's roughness is alpha's square root
            bsdf[rough_key] = {"type": "bitmap", "bitmap": _bitmap(rough), "to_uv": to_uv, "raw": True}
            self._count("varying_roughness")
        if rng.random() < 0.3:
            inner = dict(bsdf)
            bsdf.clear()  # in place: pieces of one wall share this dict
            bsdf.update(type="bumpmap", arg={"type": "bitmap", "bitmap": _bitmap(h[..., None]), "raw": True, "to_uv": to_uv},
                        scale=float(_loguniform(rng, 0.02, 0.3)), nested=inner)
            self._seen[id(inner)] = inner
            self._count("detail_bump")

    def finish(self, scene: dict) -> dict[str, int]:
        """Detail on the scene's remaining dict BSDFs, in key order; returns :attr:`added`."""
        for key in sorted(scene):
            node = scene[key]
            if isinstance(node, dict) and isinstance(node.get("bsdf"), dict):
                self(node["bsdf"])
        return dict(sorted(self.added.items()))
