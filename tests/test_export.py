"""PGM + YAML for map_server and PNG rendering."""
import io

import numpy as np
import pytest
import yaml
from PIL import Image

from mapping.errors import InputError
from mapping.export import crop_to_occupied, render_pgm, render_png


def small_map():
    probability = np.array([[0.9, 0.1, 0.5], [0.5, 0.5, 0.1]], np.float32)
    observed = np.array([[True, True, True], [False, True, True]])
    return {"probability": probability, "observed": observed, "variance": np.arange(6, dtype=np.float32).reshape(2, 3),
            "origin": np.array([-1.0, 2.0]), "resolution": 0.5}


@pytest.mark.parametrize("name", ["a #b.pgm", "c: d.pgm", "[e].pgm", "%f.pgm", "'g.pgm", "@h.pgm", 'q"uo\\te.pgm',
                                  "karte-\u00fc.pgm", "tab\there.pgm", "line\nbreak.pgm", "sep\u2028.pgm",
                                  "\ufeffbom.pgm", "smile-\U0001f600.pgm", "del\x7f\x85.pgm"])
def test_yaml_names_any_image_file_as_it_is(name):
    """As a plain YAML scalar 'a #b.pgm' read as 'a' (the rest a comment) and 'c: d.pgm' did not parse; map_server
    loaded the wrong file or none. Read back by a YAML parser, the YAML names the file exactly."""
    _, text = render_pgm(small_map(), image_name=name)
    assert yaml.safe_load(text.encode("utf-8"))["image"] == name


def test_a_file_name_that_is_not_utf8_is_refused_not_garbled():
    with pytest.raises(InputError, match="not valid UTF-8"):
        render_pgm(small_map(), image_name=b"map-\xff.pgm".decode("utf-8", "surrogateescape"))


def test_pgm_is_flipped_trinary_and_yaml_has_origin():
    pgm, yaml = render_pgm(small_map(), image_name="m.pgm")
    header, pixels = pgm[:11], np.frombuffer(pgm[11:], np.uint8).reshape(2, 3)
    assert header == b"P5\n3 2\n255\n"
    # the top image row is the raster's last row (north up): unknown, unknown(0.5), free
    assert pixels.tolist() == [[205, 205, 254], [0, 254, 205]]
    assert 'image: "m.pgm"' in yaml and "origin: [-1.000000, 2.000000, 0.0]" in yaml and "resolution: 0.500000" in yaml


def test_png_layers():
    for layer in ("probability", "variance"):
        image = Image.open(io.BytesIO(render_png(small_map(), layer=layer)))
        assert image.size == (3, 2)
    rgb = np.asarray(Image.open(io.BytesIO(render_png(small_map()))))
    # grey = 255 (1 - p): occupied (p = 0.9) is dark, at the bottom-left after the flip; free (0.1) light
    assert np.abs(rgb[1, 0].astype(int) - 25.5).max() <= 1
    assert np.abs(rgb[1, 1].astype(int) - 229.5).max() <= 1
    assert rgb[0, 0].tolist() == [180, 190, 205]  # unobserved


def test_crop_keeps_the_occupied_cells_plus_margin_and_moves_the_origin():
    probability = np.full((10, 12), 0.1, np.float32)
    probability[4, 5] = probability[6, 7] = 0.9  # occupied: rows 4..6, columns 5..7
    observed = np.ones((10, 12), bool)
    arrays = {"probability": probability, "observed": observed, "variance": np.zeros((10, 12), np.float32),
              "origin": np.array([-1.0, 2.0]), "resolution": 0.5}
    cropped = crop_to_occupied(arrays, margin=1.0)  # two cells
    assert cropped["probability"].shape == (7, 7) and cropped["variance"].shape == (7, 7)
    np.testing.assert_allclose(cropped["origin"], [-1.0 + 3 * 0.5, 2.0 + 2 * 0.5])
    assert cropped["probability"][2, 2] == np.float32(0.9) and cropped["probability"][4, 4] == np.float32(0.9)
    # the margin stops at the raster's edge
    assert crop_to_occupied(arrays, margin=100.0)["probability"].shape == (10, 12)
    with pytest.raises(InputError, match="no occupied cells"):
        crop_to_occupied({**arrays, "probability": np.full((10, 12), 0.1, np.float32)}, margin=1.0)
