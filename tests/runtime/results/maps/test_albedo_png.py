"""albedo.png: scaled to a high percentile (not to one specular speck), marked linear, and
saying so in its own text."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from msfnet.runtime.results.maps.api import (
    ALBEDO_PNG_NOTE,
    albedo_png,
    linear_png,
    png_with_text,
)
from msfnet.runtime.results.maps.pictures import png_bytes


def _albedo_with_a_speck() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    albedo = rng.uniform(0.2, 0.4, (40, 50, 3))
    albedo[10, 10] = 20.0  # one specular speck, 50x the rest
    mask = np.zeros((40, 50), bool)
    mask[5:35, 5:45] = True
    return albedo, mask


def test_a_speck_does_not_darken_the_rest() -> None:
    albedo, mask = _albedo_with_a_speck()
    img = albedo_png(albedo, mask)
    body = img[mask].max(axis=1)
    # the 99.5th percentile is white: the typical pixel sits well up the scale (scaled to
    # the speck, it was ~1.5 % of full scale: black in a viewer)
    assert np.median(body) > 0.6 * 65535, np.median(body)
    assert img[10, 10].tolist() == [65535] * 3  # the speck is clipped
    assert (img[~mask] == 0).all()
    top = np.percentile(albedo[mask].max(axis=1), 99.5)
    expect = np.clip(np.rint(albedo[20, 20] * 65535 / top), 0, 65535)
    np.testing.assert_array_equal(img[20, 20], expect)  # linear: values are proportional


def test_the_png_is_marked_linear_and_says_how_it_is_scaled() -> None:
    albedo, mask = _albedo_with_a_speck()
    raw = png_bytes(albedo_png(albedo, mask))
    data = linear_png(raw, ALBEDO_PNG_NOTE)
    im = Image.open(io.BytesIO(data))
    im.load()  # checks every chunk's CRC on the way
    assert im.info["gamma"] == 1.0
    assert "99.5th percentile" in im.info["Description"] and "albedo.tif" in im.info["Description"]
    np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(raw))), np.asarray(im))
    tagged = Image.open(io.BytesIO(png_with_text(raw, "Comment", "x")))
    assert tagged.info["Comment"] == "x"
