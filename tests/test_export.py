"""PGM + YAML for map_server and PNG rendering."""

import io

import numpy as np
import pytest
import yaml
from hypothesis import example, given
from hypothesis import strategies as st
from PIL import Image

from mapping.errors import InputError
from mapping.export import crop_to_occupied, render_pgm, render_png, render_rgb


def small_map():
    probability = np.array([[0.9, 0.1, 0.5], [0.5, 0.5, 0.1]], np.float32)
    observed = np.array([[True, True, True], [False, True, True]])
    return {
        "probability": probability,
        "observed": observed,
        "variance": np.arange(6, dtype=np.float32).reshape(2, 3),
        "origin": np.array([-1.0, 2.0]),
        "resolution": 0.5,
    }


@pytest.mark.parametrize(
    "name",
    [
        "a #b.pgm",
        "c: d.pgm",
        "[e].pgm",
        "%f.pgm",
        "'g.pgm",
        "@h.pgm",
        'q"uo\\te.pgm',
        "karte-\u00fc.pgm",
        "tab\there.pgm",
        "line\nbreak.pgm",
        "sep\u2028.pgm",
        "\ufeffbom.pgm",
        "smile-\U0001f600.pgm",
        "del\x7f\x85.pgm",
    ],
)
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
    assert 'image: "m.pgm"' in yaml and "origin: [-1.0, 2.0, 0.0]" in yaml and "resolution: 0.5" in yaml


@given(
    resolution=st.floats(1e-6, 1000.0),
    ox=st.floats(-1e7, 1e7, allow_subnormal=True),
    oy=st.floats(-1e-300, 1e-300),
)
@example(resolution=1.5e-6, ox=-12.3456789, oy=1e-7)
@example(resolution=1 / 30, ox=1e20 / 1e13, oy=0.0)
def test_yaml_gives_resolution_and_origin_exactly(resolution, ox, oy):
    """Written to six decimals, a resolution of 1.5e-6 m read back as 2e-6 (map_server drew the map a third too
    big) and 1/30 m as 0.033333. Read back by a YAML 1.1 parser (PyYAML; map_server's yaml-cpp reads YAML 1.2, which
    takes these forms too), the floats are the map's doubles exactly."""
    arrays = dict(small_map(), resolution=resolution, origin=np.array([ox, oy]))
    _, text = render_pgm(arrays)
    loaded = yaml.safe_load(text)
    assert type(loaded["resolution"]) is float and loaded["resolution"] == resolution
    assert loaded["origin"] == [ox, oy, 0.0]


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
    arrays = {
        "probability": probability,
        "observed": observed,
        "variance": np.zeros((10, 12), np.float32),
        "origin": np.array([-1.0, 2.0]),
        "resolution": 0.5,
    }
    cropped = crop_to_occupied(arrays, margin=1.0)  # two cells
    assert cropped["probability"].shape == (7, 7) and cropped["variance"].shape == (7, 7)
    np.testing.assert_allclose(cropped["origin"], [-1.0 + 3 * 0.5, 2.0 + 2 * 0.5])
    assert cropped["probability"][2, 2] == np.float32(0.9) and cropped["probability"][4, 4] == np.float32(0.9)
    # the margin stops at the raster's edge
    assert crop_to_occupied(arrays, margin=100.0)["probability"].shape == (10, 12)
    with pytest.raises(InputError, match="no occupied cells"):
        crop_to_occupied({**arrays, "probability": np.full((10, 12), 0.1, np.float32)}, margin=1.0)


def _arrays(probability, observed=None, variance=None, resolution=0.5):
    probability = np.asarray(probability, np.float32)
    return {
        "probability": probability,
        "observed": np.ones(probability.shape, bool) if observed is None else np.asarray(observed, bool),
        "variance": None if variance is None else np.asarray(variance, np.float32),
        "origin": np.array([-1.0, 2.0]),
        "resolution": resolution,
    }


def test_unobserved_cells_are_unknown_in_the_pgm_whatever_their_probability():
    """A map file from another tool may carry a probability for a cell it marks unobserved."""
    arrays = _arrays([[0.9, 0.1, 0.9, 0.1]], observed=[[False, False, True, True]])
    pgm, _ = render_pgm(arrays)
    assert pgm.endswith(bytes([205, 205, 0, 254]))


def test_crop_margin_rounds_up_to_whole_cells():
    """0.6 m at 0.5 m cells is two cells on each side (one would leave less than the margin)."""
    probability = np.full((9, 9), 0.1, np.float32)
    probability[4, 4] = 0.9
    cropped = crop_to_occupied(_arrays(probability), margin=0.6)
    assert cropped["probability"].shape == (5, 5)
    np.testing.assert_allclose(cropped["origin"], [-1.0 + 2 * 0.5, 2.0 + 2 * 0.5])


def test_crop_ignores_unobserved_cells_and_refuses_a_negative_margin():
    probability = np.full((6, 6), 0.1, np.float32)
    probability[1, 1] = probability[5, 5] = 0.9
    observed = np.ones((6, 6), bool)
    observed[5, 5] = False  # its probability says occupied, but nothing saw it
    cropped = crop_to_occupied(_arrays(probability, observed), margin=0.0)
    assert cropped["probability"].shape == (1, 1)
    np.testing.assert_allclose(cropped["origin"], [-1.0 + 0.5, 2.0 + 0.5])
    with pytest.raises(InputError, match="margin must be >= 0"):
        crop_to_occupied(_arrays(probability, observed), margin=-0.5)


def test_variance_colours_follow_the_ramp_and_the_99th_percentile_scale():
    """Variances 0 .. 100 in one row: the default scale is their 99th percentile, 99. A cell of 66 is at 2/3 of the
    ramp (its third stop, 250 170 20), 0 is black, and 99 and 100 reach the last stop (255 255 230)."""
    variance = np.arange(101, dtype=np.float32)[None, :]
    rgb = render_rgb(_arrays(np.full((1, 101), 0.5), variance=variance), layer="variance").astype(int)
    assert rgb[0, 0].tolist() == [0, 0, 0]
    assert np.abs(rgb[0, 66] - [250, 170, 20]).max() <= 1
    assert np.abs(rgb[0, 33] - [170, 20, 30]).max() <= 1
    assert rgb[0, 100].tolist() == [255, 255, 230] and np.abs(rgb[0, 99] - [255, 255, 230]).max() <= 1


def test_an_all_zero_variance_layer_renders_black_not_garbage():
    rgb = render_rgb(_arrays(np.full((2, 2), 0.5), variance=np.zeros((2, 2))), layer="variance")
    assert rgb.tolist() == [[[0, 0, 0]] * 2] * 2


def test_a_tall_map_renders_in_bands_as_whole_and_in_bounded_memory():
    """A probe: a variance PNG took about 130 bytes a cell (float64 copies of the whole map: 4.35 GB for a 33 M-cell
    map, 1.2 GB more in the API for one export). Rendered in bands of rows, the same pixels as the ramp applied to the
    whole map at once, in a fraction of the memory."""
    import tracemalloc

    from mapping.export import RENDER_ROWS, UNOBSERVED_RGB, _heat, render_rgb

    rng = np.random.default_rng(0)
    rows, cols = 8 * RENDER_ROWS + 37, 200
    arrays = {
        "probability": rng.random((rows, cols)).astype(np.float32),
        "variance": (rng.random((rows, cols)) ** 3).astype(np.float32),
        "observed": rng.random((rows, cols)) < 0.8,
    }
    scale = float(np.percentile(arrays["variance"][arrays["observed"]].astype(float), 99))
    expected = {
        "probability": np.repeat(
            np.round(255 * (1.0 - arrays["probability"].astype(float))).astype(np.uint8)[..., None], 3, 2
        ),
        "variance": _heat(arrays["variance"].astype(float) / scale),
    }
    for layer, whole in expected.items():
        whole[~arrays["observed"]] = UNOBSERVED_RGB
        np.testing.assert_array_equal(render_rgb(arrays, layer), whole)
    tracemalloc.start()
    render_rgb(arrays, "variance")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak / (rows * cols) < 40  # bytes a cell: the image's 3, the percentile's 8 an observed cell, one band's
