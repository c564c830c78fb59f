"""A tile's layers, or an exported map's, as bytes: PNG for people (mapping.export's colours), .npz in the
map-file format, and for an export also a zip of a PGM and its YAML for ROS map_server.

PNG tiles are north up (row 0 of the raster, the southern-most, is the image's bottom row), one pixel per
cell. Layers: probability (grey level 1 - p: free light, occupied black), variance (the black-red-yellow ramp over
variance / vmax) and logodds (grey, linear from the map's lower clamp, white, to its upper clamp, black);
unobserved cells are pale blue-grey in all three.
"""

from __future__ import annotations

import io
import math
import zipfile

import numpy as np
from PIL import Image

from mapping.export import UNOBSERVED_RGB, render_pgm, render_png
from mapping.grid import probability_of
from mapping.pyramid import TileLayers
from schemas.files import MapFile, save_map, write_npz_deterministic

LAYERS = ("probability", "logodds", "variance")

#: the log-odds range the logodds PNG spans: the clamping range [logit(0.12), logit(0.97)] of the sensor model
#: posegrid maps with (mapping.sensor_model.SensorModel's p_min, p_max; written out so that the API does not
#: load scipy at start-up, and checked against it by tests/test_api_units.py)
LOGODDS_RANGE = (math.log(0.12 / 0.88), math.log(0.97 / 0.03))


def empty_layers(tile_size: int) -> TileLayers:
    """The layers of a tile no scan has touched."""
    shape = (tile_size, tile_size)
    return np.zeros(shape, np.float32), np.zeros(shape, np.float32), np.zeros(shape, bool)


def png_bytes(layers: TileLayers, layer: str, vmax: float | None) -> bytes:
    """PNG of one layer; ``vmax`` is the variance that maps to the top of the variance ramp (None: the 99th
    percentile of the observed cells' variance)."""
    logodds, variance, observed = layers
    if layer == "logodds":
        low, high = LOGODDS_RANGE
        grey = np.round(255 * (1.0 - np.clip((logodds - low) / (high - low), 0.0, 1.0))).astype(np.uint8)
        rgb = np.repeat(grey[..., None], 3, axis=2)
        rgb[~observed] = UNOBSERVED_RGB
        buffer = io.BytesIO()
        Image.fromarray(np.flipud(rgb)).save(buffer, format="PNG")
        return buffer.getvalue()
    arrays = {"probability": probability_of(logodds), "observed": observed, "variance": variance}
    return render_png(arrays, layer, variance_scale=vmax)


def npz_bytes(layers: TileLayers, layer: str | None, origin: tuple[float, float], resolution: float) -> bytes:
    """A tile as .npz: a complete map file (docs/formats.md) when ``layer`` is None, else only that layer
    with ``observed``, ``origin`` and ``resolution``."""
    logodds, variance, observed = layers
    buffer = io.BytesIO()
    if layer is None:
        save_map(
            buffer,
            MapFile(
                logodds=logodds,
                probability=probability_of(logodds),
                observed=observed,
                origin=np.asarray(origin, np.float64),
                resolution=resolution,
                variance=variance,
            ),
        )
    else:
        values = {"logodds": logodds, "probability": probability_of(logodds), "variance": variance}[layer]
        write_npz_deterministic(
            buffer,
            {
                layer: values,
                "observed": observed,
                "origin": np.asarray(origin, np.float64),
                "resolution": np.float64(resolution),
            },
        )
    return buffer.getvalue()


#: the time stamp of every member of an export's zip (fixed, so that the same map gives the same bytes)
ZIP_TIME = (1980, 1, 1, 0, 0, 0)


def pgm_zip(raster: dict, name: str) -> bytes:
    """A zip of ``name``.pgm and ``name``.yaml, the map_server image of a rasterized map (mapping.export.render_pgm;
    ``raster`` as mapping.grid.TiledGrid.rasterize returns it)."""
    pgm, yaml = render_pgm(raster, image_name=f"{name}.pgm")
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr(zipfile.ZipInfo(f"{name}.pgm", date_time=ZIP_TIME), pgm)
        archive.writestr(zipfile.ZipInfo(f"{name}.yaml", date_time=ZIP_TIME), yaml)
    return buffer.getvalue()


def export_body(raster: dict, name: str, fmt: str, layer: str | None) -> tuple[bytes, str, str]:
    """(body, media type, file name) of the export of map ``name`` in format ``fmt`` (npz, pgm or png; layer as
    GET /maps/{map}/export takes it); ``raster`` as mapping.grid.TiledGrid.rasterize returns it."""
    layers = (raster["logodds"], raster["variance"], raster["observed"])
    if fmt == "npz":
        return (
            npz_bytes(layers, layer, raster["origin"], float(raster["resolution"])),
            "application/octet-stream",
            f"{name}.npz",
        )
    if fmt == "pgm":
        return pgm_zip(raster, name), "application/zip", f"{name}.zip"
    return png_bytes(layers, layer or "probability", None), "image/png", f"{name}.png"
