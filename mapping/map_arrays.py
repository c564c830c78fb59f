"""The check of a map given as a dict of map-file keys (``probability``, ``observed``, ``variance``, ``origin``,
``resolution``: docs/formats.md) before it is drawn (mapping.export) or scored (mapping.evaluation), written once.
A map loaded with schemas.files.load_map has passed the file contract's own checks; this catches a map built in
code, whose wrong values would otherwise be drawn or scored without a word.
"""

from __future__ import annotations

import numpy as np

from mapping.errors import InputError


def check_raster(map_arrays: dict, layer: str = "probability", frame: bool = True) -> None:
    """Refuse a map dict that would be drawn or scored wrongly: ``probability`` (or ``layer``) and ``observed`` not of
    one 2-D shape (``observed`` may be absent), a probability outside [0, 1] or NaN (drawn black, as if occupied), a
    NaN, inf or negative variance, and with ``frame`` an origin (2 m) or resolution (m, > 0) that is not finite."""
    values = np.asarray(map_arrays[layer], np.float64)
    observed = map_arrays.get("observed")
    shape = values.shape if observed is None else np.shape(observed)
    if values.ndim != 2 or values.shape != shape:
        raise InputError(f"'{layer}' and 'observed' must be 2-D of one shape, got {values.shape} and {shape}")
    low, high = (0.0, 1.0) if layer == "probability" else (0.0, np.inf)
    bad = ~(np.isfinite(values) & (values >= low) & (values <= high))
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InputError(f"'{layer}' holds {values[index]} at {index}; it must be finite and in [{low:g}, {high:g}]")
    if not frame:
        return
    origin = np.asarray(map_arrays["origin"], np.float64)
    resolution = float(map_arrays["resolution"])
    if origin.shape != (2,) or not np.isfinite(origin).all() or not (np.isfinite(resolution) and resolution > 0):
        raise InputError(
            f"the map needs a finite origin (x m, y m) and a resolution > 0 m, got {origin.tolist()} and {resolution}"
        )
