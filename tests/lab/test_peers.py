"""Tests for clipgs_jax/lab/peers.py without the peers' sources: the
COLMAP folder the peers train on, and the checks before any run."""

import numpy as np
import pytest

from clipgs_jax.data import default_scene
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.lab import peers


def test_write_colmap_reloads_as_the_same_views(tmp_path):
  source = scene_lib.load_scene(default_scene.ensure_default_scene())
  folder = str(tmp_path / "peer_scene")
  peers.write_colmap(source.train, source.points, source.point_colors,
                     folder)
  again = scene_lib.load_scene(folder, cache_dir=str(tmp_path / "cache"))
  # Every view comes back, whichever split it lands in: cameras, photos
  # (8-bit PNG) and points.
  seen = 0
  for part in (again.train, again.test):
    for j, name in enumerate(part.names):
      i = int(name[:5])
      seen += 1
      for field in ("rotation", "translation", "fx", "fy", "cx", "cy"):
        np.testing.assert_allclose(getattr(part.cameras, field)[j],
                                   getattr(source.train.cameras, field)[i],
                                   atol=1e-5, err_msg=field)
      np.testing.assert_allclose(part.images[j], source.train.images[i],
                                 atol=0.5 / 255 + 1e-6)
  assert seen == len(source.train)
  np.testing.assert_allclose(again.points, source.points, atol=1e-6)


def test_missing_names_the_folder_and_the_fix(tmp_path):
  lines = peers.missing(str(tmp_path), ["ghif", "nerfstudio"])
  assert len(lines) == 2
  assert str(tmp_path / "ghif-jax-gs" / "train.py") in lines[0]
  assert "bench_peers/README.md" in lines[0]
  assert "not a peer" in lines[1]


def test_bench_refuses_before_reading_the_scene(tmp_path):
  with pytest.raises(ValueError) as e:
    peers.bench(str(tmp_path), ["ghif"], str(tmp_path / "no_scene"), 8,
                1500, 0, str(tmp_path / "out"))
  assert "ghif-jax-gs" in str(e.value) and "steps=1500" in str(e.value)
  assert not (tmp_path / "out").exists()
