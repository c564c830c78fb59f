"""PGM + YAML for map_server and PNG rendering."""
import io

import numpy as np
from PIL import Image

from mapping.export import render_pgm, render_png


def small_map():
    probability = np.array([[0.9, 0.1, 0.5], [0.5, 0.5, 0.1]], np.float32)
    observed = np.array([[True, True, True], [False, True, True]])
    return {"probability": probability, "observed": observed, "variance": np.arange(6, dtype=np.float32).reshape(2, 3),
            "origin": np.array([-1.0, 2.0]), "resolution": 0.5}


def test_pgm_is_flipped_trinary_and_yaml_has_origin():
    pgm, yaml = render_pgm(small_map(), image_name="m.pgm")
    header, pixels = pgm[:11], np.frombuffer(pgm[11:], np.uint8).reshape(2, 3)
    assert header == b"P5\n3 2\n255\n"
    # the top image row is the raster's last row (north up): unknown, unknown(0.5), free
    assert pixels.tolist() == [[205, 205, 254], [0, 254, 205]]
    assert "image: m.pgm" in yaml and "origin: [-1.000000, 2.000000, 0.0]" in yaml and "resolution: 0.500000" in yaml


def test_png_layers():
    for layer in ("probability", "variance"):
        image = Image.open(io.BytesIO(render_png(small_map(), layer=layer)))
        assert image.size == (3, 2)
    rgb = np.asarray(Image.open(io.BytesIO(render_png(small_map()))))
    # grey = 255 (1 - p): occupied (p = 0.9) is dark, at the bottom-left after the flip; free (0.1) light
    assert np.abs(rgb[1, 0].astype(int) - 25.5).max() <= 1
    assert np.abs(rgb[1, 1].astype(int) - 229.5).max() <= 1
    assert rgb[0, 0].tolist() == [180, 190, 205]  # unobserved
