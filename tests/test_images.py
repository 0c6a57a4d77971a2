"""Tests for data/images.py: decoding, resizing, the cache and PNG output."""

import os

import numpy as np
import OpenImageIO as oiio
import pytest

from clipgs_jax.data import images


def _write_raw(path, pixels, **attributes):
  """Writes native-typed pixels [H, W, C] with OpenImageIO, unconverted."""
  fmt = {np.uint8: "uint8", np.uint16: "uint16"}[pixels.dtype.type]
  spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], fmt)
  spec.attribute("oiio:UnassociatedAlpha", 1)
  for key, value in attributes.items():
    spec.attribute(key, value)
  out = oiio.ImageOutput.create(str(path))
  assert out.open(str(path), spec), out.geterror()
  assert out.write_image(pixels)
  out.close()


def test_8bit_rgb(tmp_path):
  pixels = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3) * 4
  _write_raw(tmp_path / "a.png", pixels)
  image = images.read_image(str(tmp_path / "a.png"))
  assert image.dtype == np.float32 and image.shape == (4, 5, 3)
  np.testing.assert_array_equal(image, pixels.astype(np.float32) / 255)


def test_16bit_keeps_precision(tmp_path):
  pixels = (np.arange(4 * 5 * 3, dtype=np.uint16).reshape(4, 5, 3) +
            30000)                     # neighbours differ by 1 / 65535
  _write_raw(tmp_path / "a.png", pixels)
  image = images.read_image(str(tmp_path / "a.png"))
  np.testing.assert_allclose(image, pixels / 65535.0, atol=1e-7)
  assert len(np.unique(image)) == pixels.size


def test_grey_is_replicated(tmp_path):
  pixels = np.array([[[0], [128]], [[255], [7]]], np.uint8)
  _write_raw(tmp_path / "g.png", pixels)
  image = images.read_image(str(tmp_path / "g.png"))
  assert image.shape == (2, 2, 3)
  np.testing.assert_array_equal(image, np.repeat(pixels / 255.0, 3, -1)
                                .astype(np.float32))


def test_grey_alpha(tmp_path):
  pixels = np.array([[[200, 0], [100, 255]]], np.uint8)
  _write_raw(tmp_path / "ga.png", pixels)
  image = images.read_image(str(tmp_path / "ga.png"))
  np.testing.assert_allclose(image[0, :, 0], [200 / 255, 100 / 255])
  np.testing.assert_array_equal(image[..., 0], image[..., 2])


def test_rgba_drops_alpha_without_premultiplying(tmp_path):
  pixels = np.zeros((2, 3, 4), np.uint8)
  pixels[..., 0], pixels[..., 1], pixels[..., 3] = 204, 51, 128
  _write_raw(tmp_path / "rgba.png", pixels)
  image = images.read_image(str(tmp_path / "rgba.png"))
  assert image.shape == (2, 3, 3)
  # Premultiplied would read 0.4; the stored colour is 0.8.
  np.testing.assert_allclose(image[0, 0], [0.8, 0.2, 0.0], atol=1e-6)


def test_exif_orientation_is_not_applied(tmp_path):
  pixels = np.zeros((4, 8, 3), np.uint8)
  pixels[0, 0] = 255
  path = tmp_path / "rot.jpg"
  _write_raw(path, pixels, Orientation=6)       # "rotate 90 CW to display"
  inp = oiio.ImageInput.open(str(path))
  assert inp.spec().get_int_attribute("Orientation") == 6
  inp.close()
  image = images.read_image(str(path))
  assert image.shape == (4, 8, 3)              # stored grid, not rotated
  assert image[0, 0, 0] > 0.5 and image[-1, -1, 0] < 0.2


def test_missing_and_corrupt_files(tmp_path):
  with pytest.raises(FileNotFoundError, match="nope.png"):
    images.read_image(str(tmp_path / "nope.png"))
  bad = tmp_path / "bad.png"
  bad.write_bytes(b"\x89PNG garbage" * 10)
  with pytest.raises(ValueError) as e:
    images.read_image(str(bad))
  assert str(bad) in str(e.value) and "\n" not in str(e.value)
  with pytest.raises(FileNotFoundError):
    images.image_size(str(tmp_path / "nope.png"))


def test_image_size_reads_header(tmp_path):
  _write_raw(tmp_path / "a.png", np.zeros((7, 9, 3), np.uint8))
  assert images.image_size(str(tmp_path / "a.png")) == (9, 7)


def test_downscaled_size():
  assert images.downscaled_size(544, 960, 4) == (136, 240)
  # Non-divisible sizes round half up: 272.5 -> 273, 480.5 -> 481.
  assert images.downscaled_size(545, 961, 2) == (273, 481)
  assert images.downscaled_size(3, 3, 8) == (1, 1)
  for bad in (0, -2, 1.5):
    with pytest.raises(ValueError, match="downscale factor"):
      images.downscaled_size(10, 10, bad)


def test_resize_integer_factor_is_block_mean():
  x = np.random.default_rng(0).random((12, 20, 3)).astype(np.float32)
  expected = x.reshape(3, 4, 5, 4, 3).mean(axis=(1, 3))
  np.testing.assert_allclose(images.resize_area(x, 5, 3), expected,
                             atol=1e-6)


def test_resize_fractional_factor():
  # 3 -> 2 pixels: output 0 covers [0, 1.5): (0 * 1 + 3 * 0.5) / 1.5 = 1;
  # output 1 covers [1.5, 3): (3 * 0.5 + 6 * 1) / 1.5 = 5.
  row = np.array([[0.0, 3.0, 6.0]])
  np.testing.assert_allclose(images.resize_area(row, 2, 1), [[1.0, 5.0]])
  x = np.random.default_rng(1).random((13, 17))
  y = images.resize_area(x, 7, 5)
  assert y.shape == (5, 7)
  np.testing.assert_allclose(y.mean(), x.mean(), rtol=1e-5)   # area kept
  np.testing.assert_allclose(images.resize_area(np.full((9, 7, 3), 0.3), 4, 4),
                             0.3, atol=1e-6)


def test_load_image_caches_the_resize(tmp_path):
  x = np.random.default_rng(2).random((10, 14, 3))
  src = tmp_path / "src.png"
  images.write_png(str(src), x, bits=16)
  cache = tmp_path / "cache"
  first = images.load_image(str(src), factor=2, expected_size=(14, 10),
                            cache_dir=str(cache))
  assert first.shape == (5, 7, 3)
  np.testing.assert_allclose(
      first, images.resize_area(images.read_image(str(src)), 7, 5),
      atol=1e-5)
  files = os.listdir(cache)
  assert len(files) == 1 and files[0].endswith("src.png.png")
  # A cache hit returns the same values bit for bit.
  second = images.load_image(str(src), factor=2, cache_dir=str(cache))
  np.testing.assert_array_equal(first, second)
  # A changed source is not served from the stale cache entry.
  images.write_png(str(src), np.zeros((10, 14, 3)), bits=16)
  os.utime(src, ns=(1, 1))
  third = images.load_image(str(src), factor=2, cache_dir=str(cache))
  np.testing.assert_array_equal(third, 0)


def test_load_image_size_mismatch(tmp_path):
  images.write_png(str(tmp_path / "a.png"), np.zeros((10, 14, 3)))
  for factor in (1, 2):
    with pytest.raises(ValueError) as e:
      images.load_image(str(tmp_path / "a.png"), factor=factor,
                        expected_size=(16, 10))
    assert str(tmp_path / "a.png") in str(e.value)
    assert "14x10" in str(e.value) and "16x10" in str(e.value)


def test_load_image_prefers_prescaled(tmp_path):
  images.write_png(str(tmp_path / "full.png"), np.zeros((40, 60, 3)))
  images.write_png(str(tmp_path / "small.png"), np.ones((10, 15, 3)))
  image = images.load_image(str(tmp_path / "full.png"), factor=4,
                            expected_size=(60, 40),
                            prescaled_path=str(tmp_path / "small.png"))
  np.testing.assert_array_equal(image, 1.0)
  images.write_png(str(tmp_path / "wrong.png"), np.ones((12, 15, 3)))
  with pytest.raises(ValueError, match="wrong.png"):
    images.load_image(str(tmp_path / "full.png"), factor=4,
                      expected_size=(60, 40),
                      prescaled_path=str(tmp_path / "wrong.png"))


def test_write_png(tmp_path):
  x = np.random.default_rng(3).random((6, 5, 3)) * 1.2 - 0.1
  path = tmp_path / "sub" / "out.png"
  images.write_png(str(path), x)
  back = images.read_image(str(path))
  np.testing.assert_allclose(back, np.clip(x, 0, 1), atol=0.5 / 255 + 1e-6)
  inp = oiio.ImageInput.open(str(path))
  assert inp.spec().format == oiio.TypeDesc("uint8")
  inp.close()
  assert os.listdir(path.parent) == ["out.png"]        # no temp files left
  mask = np.zeros((3, 4), bool)
  mask[1, 2] = True
  images.write_png(str(tmp_path / "m.png"), mask)
  np.testing.assert_array_equal(images.read_image(str(tmp_path / "m.png"))
                                [..., 0], mask.astype(np.float32))
  with pytest.raises(ValueError, match="shape"):
    images.write_png(str(tmp_path / "x.png"), np.zeros((2, 3, 5)))
  with pytest.raises(ValueError, match="dtype"):
    images.write_png(str(tmp_path / "x.png"), np.zeros((2, 3), np.uint8))
