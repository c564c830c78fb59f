"""Rendering a map raster for people (PNG) and for ROS map_server (PGM + YAML).

Input is a dict with the map file's keys (``probability``, ``observed``, ``variance``, ``origin``,
``resolution``); row 0 of the raster is the southern-most row (y grows with the row index), so images are
flipped vertically to put north up, as map_server expects.
"""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from mapping.errors import InputError
from mapping.map_arrays import check_raster

LAYERS = ("probability", "variance")

#: map_server's conventional thresholds and pixel values (negate: 0)
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205

UNOBSERVED_RGB = (180, 190, 205)


def occupancy_pixels(probability: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """map_server trinary pixels (uint8, raster row order): occupied 0, free 254, unknown 205."""
    pixels = np.full(probability.shape, PGM_UNKNOWN, np.uint8)
    pixels[observed & (probability >= OCCUPIED_THRESH)] = PGM_OCCUPIED
    pixels[observed & (probability <= FREE_THRESH)] = PGM_FREE
    return pixels


def _yaml_printable(code: int) -> bool:
    """Whether a code point may stand as itself in a YAML double-quoted scalar (YAML 1.2's printable set, less
    the line and paragraph separators and the byte order mark, which readers treat specially)."""
    return 0x20 <= code <= 0x7E or (0xA0 <= code <= 0xFFFD and code not in (0x2028, 0x2029, 0xFEFF)) or code >= 0x10000


def _yaml_quoted(text: str) -> str:
    """``text`` as a YAML double-quoted scalar (YAML 1.2, section 5.7), others escaped, so that a file name with
    '#', ': ' or '[' stays the name: as a plain scalar, 'a #b.pgm' read as 'a' and 'c: d.pgm' did not parse."""
    if any(0xD800 <= ord(char) <= 0xDFFF for char in text):  # an undecodable byte of the file system's name
        raise InputError(f"the image name {text!r} is not valid UTF-8; a YAML file cannot name it")
    escaped = (
        "\\" + char
        if char in '"\\'
        else char
        if _yaml_printable(ord(char))
        else f"\\x{ord(char):02x}"
        if ord(char) < 0x100
        else f"\\u{ord(char):04x}"
        for char in text
    )
    return '"' + "".join(escaped) + '"'


def _yaml_float(value: float) -> str:
    """``value`` (finite) as a YAML float that reads back as the same double: Python's shortest round-trip form,
    with a '.' in the mantissa, since YAML 1.1 parsers (PyYAML) read '1e-06' as a string."""
    text = repr(float(value))
    mantissa, sep, exponent = text.partition("e")
    if sep and "." not in mantissa:
        return f"{mantissa}.0e{exponent}"
    return text


def render_pgm(map_arrays: dict, image_name: str = "map.pgm") -> tuple[bytes, str]:
    """A binary PGM (P5) and its map_server YAML; the YAML names the image file ``image_name``."""
    check_raster(map_arrays)
    pixels = np.flipud(occupancy_pixels(np.asarray(map_arrays["probability"]), np.asarray(map_arrays["observed"])))
    if pixels.size == 0:
        raise InputError("the map is empty (no cells); a 0 x 0 image is no map for map_server")
    height, width = pixels.shape
    pgm = f"P5\n{width} {height}\n255\n".encode("ascii") + pixels.tobytes()
    ox, oy = (float(v) for v in map_arrays["origin"])
    yaml = (
        f"image: {_yaml_quoted(image_name)}\n"
        f"resolution: {_yaml_float(map_arrays['resolution'])}\n"
        f"origin: [{_yaml_float(ox)}, {_yaml_float(oy)}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n"
        "mode: trinary\n"
    )
    return pgm, yaml


def crop_to_occupied(map_arrays: dict, margin: float) -> dict:
    """The map cut to the bounding box of its occupied cells (observed, p >= OCCUPIED_THRESH) grown by
    ``margin`` m on every side, origin moved to match; every (H, W) layer is cut alike. Rays that found no
    return clear space far beyond any wall; this keeps an image to the mapped structure."""
    if not margin >= 0:  # (also NaN)
        raise InputError(f"the crop margin must be >= 0 m, got {margin}")
    check_raster(map_arrays)
    occupied = np.asarray(map_arrays["observed"], bool) & (np.asarray(map_arrays["probability"]) >= OCCUPIED_THRESH)
    if not occupied.any():
        raise InputError("the map has no occupied cells to crop to")
    rows, cols = np.flatnonzero(occupied.any(axis=1)), np.flatnonzero(occupied.any(axis=0))
    pad = int(np.ceil(min(margin / float(map_arrays["resolution"]), max(occupied.shape))))  # no wider than the map
    r0, r1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, occupied.shape[0])
    c0, c1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, occupied.shape[1])
    cropped = {
        key: (value[r0:r1, c0:c1] if isinstance(value, np.ndarray) and value.shape == occupied.shape else value)
        for key, value in map_arrays.items()
    }
    cropped["origin"] = np.asarray(map_arrays["origin"], float) + float(map_arrays["resolution"]) * np.array([c0, r0])
    return cropped


#: rows of a raster rendered at a time: the colour arithmetic's float64 temporaries take about 130 bytes a cell of a
#: band, not of the whole map (a variance PNG of a 33 M-cell map peaked at 4.35 GB)
RENDER_ROWS = 256


def _heat(values: np.ndarray) -> np.ndarray:
    """A black-red-yellow-white colour ramp for values in [0, 1] -> uint8 RGB."""
    v = np.clip(values, 0.0, 1.0)[..., None]
    stops = np.array([[0, 0, 0], [170, 20, 30], [250, 170, 20], [255, 255, 230]], float)
    pos = v * (len(stops) - 1)
    low = np.clip(np.floor(pos).astype(int), 0, len(stops) - 2)
    frac = pos - low
    rgb = stops[low[..., 0]] * (1 - frac) + stops[low[..., 0] + 1] * frac
    return rgb.astype(np.uint8)


def render_rgb(map_arrays: dict, layer: str = "probability", variance_scale: float | None = None) -> np.ndarray:
    """An RGB image (H, W, 3) uint8 in raster row order (not flipped).

    probability: grey level 1 - p, so free cells are light (224 at the 0.12 clamp) and occupied ones black;
    variance: the heat ramp over variance / variance_scale (default: the 99th percentile of observed cells).
    Unobserved cells are a pale blue-grey.
    """
    if layer not in LAYERS:
        raise InputError(f"layer must be one of {', '.join(LAYERS)}, got {layer!r}")
    if layer == "variance" and map_arrays.get("variance") is None:
        raise InputError("this map has no variance layer")
    check_raster(map_arrays, layer, frame=False)
    if variance_scale is not None and not (np.isfinite(variance_scale) and variance_scale >= 0):
        raise InputError(f"the variance scale must be finite and >= 0, got {variance_scale}")
    observed = np.asarray(map_arrays["observed"], bool)
    values = np.asarray(map_arrays[layer])
    if layer == "variance" and variance_scale is None:
        seen = np.asarray(values[observed], float)
        variance_scale = float(np.percentile(seen, 99)) if seen.size else 1.0
    scale = max(variance_scale or 0.0, 1e-12)  # (variance only)
    rgb = np.empty((*observed.shape, 3), np.uint8)
    for top in range(0, observed.shape[0], RENDER_ROWS):  # (in bands: a map's float64 copies were 130 bytes a cell)
        band = np.asarray(values[top : top + RENDER_ROWS], float)
        if layer == "probability":
            rgb[top : top + RENDER_ROWS] = np.round(255 * (1.0 - band)).astype(np.uint8)[..., None]
        else:
            rgb[top : top + RENDER_ROWS] = _heat(band / scale)
    rgb[~observed] = UNOBSERVED_RGB
    return rgb


def render_png(map_arrays: dict, layer: str = "probability", variance_scale: float | None = None) -> bytes:
    """PNG bytes of :func:`render_rgb`, north up."""
    rgb = render_rgb(map_arrays, layer, variance_scale)
    if rgb.size == 0:
        raise InputError("the map is empty (no observed cells); nothing to render")
    buffer = io.BytesIO()
    Image.fromarray(np.flipud(rgb)).save(buffer, format="PNG")
    return buffer.getvalue()
