"""data.reconstruct: input checks, real SfM (the orbit check: test_colmap)."""

import os

import numpy as np
import pycolmap
import pytest

from clipgs_jax.data import reconstruct
import shared_data  # tests/, on sys.path under pytest

DATA = shared_data.DATA
needs_data = shared_data.needs_data("bird")


def test_check_inputs_names_the_problem(tmp_path):
  with pytest.raises(ValueError, match="--images=.*no such folder"):
    reconstruct.check_inputs(str(tmp_path / "nope"), str(tmp_path), "PINHOLE")
  photos = tmp_path / "photos"
  photos.mkdir()
  for name in ("a.jpg", "b.JPG", "notes.txt"):
    (photos / name).write_bytes(b"x")
  with pytest.raises(ValueError, match="2 photos.*at least 3"):
    reconstruct.check_inputs(str(photos), str(tmp_path / "w"), "PINHOLE")
  (photos / "c.png").write_bytes(b"x")
  assert reconstruct.check_inputs(str(photos), str(tmp_path / "w"),
                                  "PINHOLE") == ["a.jpg", "b.JPG", "c.png"]
  with pytest.raises(ValueError, match="--camera_model=FISH"):
    reconstruct.check_inputs(str(photos), str(tmp_path / "w"), "FISH")
  os.makedirs(tmp_path / "w" / "sparse")
  with pytest.raises(ValueError, match="already holds sparse"):
    reconstruct.check_inputs(str(photos), str(tmp_path / "w"), "PINHOLE")


def _similarity_residual(src, dst):
  """RMS of dst - (s R src + t) after the best similarity (Umeyama),
  relative to the spread of dst."""
  mu_s, mu_d = src.mean(0), dst.mean(0)
  a, b = src - mu_s, dst - mu_d
  u, sig, vt = np.linalg.svd(b.T @ a)
  d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
  rot = u @ d @ vt
  scale = np.trace(np.diag(sig) @ d) / np.sum(a ** 2)
  fitted = scale * a @ rot.T
  return np.sqrt(np.mean(np.sum((b - fitted) ** 2, 1)) / np.mean(
      np.sum(b ** 2, 1)))


@needs_data
def test_recovers_the_shared_bird_poses(tmp_path):
  """Every 4th of the first 48 bird photos (a ~90 degree arc; consecutive
  ones are too close for a stable small model): every one registers, and
  the camera centres match the shared (known-good) bird model up to a
  similarity (measured 3.4 % of the spread)."""
  names = sorted(os.listdir(DATA / "bird" / "images"))[:48:4]
  photos = tmp_path / "photos"
  photos.mkdir()
  for name in names:
    os.symlink(DATA / "bird" / "images" / name, photos / name)
  rec = reconstruct.reconstruct(str(photos), str(tmp_path / "scene"),
                                "SIMPLE_PINHOLE", single_camera=True)
  assert rec.num_reg_images() == 12
  assert reconstruct.summary(rec).startswith("12 photos registered")
  assert (tmp_path / "scene" / "sparse" / "0" / "images.bin").is_file()
  assert os.path.realpath(tmp_path / "scene" / "images") == str(photos)
  ours = {im.name: im.projection_center() for im in rec.images.values()}
  ref_rec = pycolmap.Reconstruction(str(DATA / "bird" / "sparse" / "0"))
  ref = {im.name: im.projection_center() for im in ref_rec.images.values()}
  src = np.array([ours[n] for n in names])
  dst = np.array([ref[n] for n in names])
  assert _similarity_residual(src, dst) < 0.05
