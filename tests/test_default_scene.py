"""Tests for data/default_scene.py: determinism, layout, masks, loading."""

import json
import os
import shutil

import numpy as np
import pytest

from clipgs_jax import camera
from clipgs_jax.data import default_scene
from clipgs_jax.data import images
from clipgs_jax.data import scene


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
  return default_scene.ensure_default_scene(
      str(tmp_path_factory.mktemp("default_a")))


@pytest.fixture(scope="module")
def manifest(scene_dir):
  with open(os.path.join(scene_dir, "transients.json")) as f:
    return json.load(f)


@pytest.fixture(scope="module")
def loaded(scene_dir, tmp_path_factory):
  return scene.load_scene(scene_dir,
                          cache_dir=str(tmp_path_factory.mktemp("cache")))


def _all_files(root):
  out = {}
  for folder, _, files in os.walk(root):
    for f in files:
      path = os.path.join(folder, f)
      with open(path, "rb") as fh:
        out[os.path.relpath(path, root)] = fh.read()
  return out


def test_deterministic(scene_dir, tmp_path):
  other = default_scene.ensure_default_scene(str(tmp_path))
  a, b = _all_files(scene_dir), _all_files(other)
  assert sorted(a) == sorted(b)
  for name in a:
    assert a[name] == b[name], name


def test_layout(scene_dir, manifest):
  names = sorted(os.listdir(os.path.join(scene_dir, "images")))
  n, m = default_scene.NUM_TRAIN, default_scene.NUM_TEST
  assert names == sorted([f"0clean{i:03d}.png" for i in range(n)] +
                         [f"1extra{i:03d}.png" for i in range(m)] +
                         [f"2clutter{i:03d}.png" for i in range(n)])
  assert sorted(os.listdir(os.path.join(scene_dir, "masks"))) == [
      f"2clutter{i:03d}.png" for i in range(n)]
  for f in ("cameras.bin", "images.bin", "points3D.bin"):
    assert os.path.isfile(os.path.join(scene_dir, "sparse", "0", f))
  with open(os.path.join(scene_dir, "README.txt")) as f:
    assert "CC0" in f.read()
  assert [v["name"] for v in manifest["views"]] == [
      f"2clutter{i:03d}.png" for i in range(n)]
  image = images.read_image(os.path.join(scene_dir, "images", names[0]))
  assert image.shape == (default_scene.HEIGHT, default_scene.WIDTH, 3)
  assert image.std() > 0.05                     # a textured, non-flat image


def test_masks_match_transients(scene_dir, manifest):
  with_transients = 0
  for view in manifest["views"]:
    mask = images.read_image(os.path.join(scene_dir, view["mask"]))[..., 0]
    assert set(np.unique(mask)) <= {0.0, 1.0}
    mask = mask > 0.5
    assert mask.sum() == view["transient_pixels"]
    assert mask.any() == bool(view["transients"]), view["name"]
    with_transients += bool(view["transients"])
    clutter = images.read_image(os.path.join(scene_dir, "images",
                                             view["name"]))
    clean = images.read_image(os.path.join(scene_dir, "images",
                                           view["clean"]))
    # Transients change exactly the masked pixels: outside the mask the
    # cluttered view equals its clean twin bit for bit.
    np.testing.assert_array_equal(clutter[~mask], clean[~mask])
    if mask.any():
      assert np.abs(clutter[mask] - clean[mask]).max() > 0.2
  # Every training view is cluttered, with a sizeable share of its pixels.
  assert with_transients == default_scene.NUM_TRAIN
  share = np.mean([v["transient_pixels"] for v in manifest["views"]]) / (
      default_scene.WIDTH * default_scene.HEIGHT)
  assert 0.05 < share < 0.4, share


def _anchor(obj):
  """A 3D point inside the object, for projecting it into a view."""
  x, y, z = obj["position"]
  if obj["kind"] == "person":
    return np.array([x, y, 0.5 * obj["height"]])
  if obj["kind"] == "crate":
    return np.array([x, y, obj["half"][2]])
  return np.array([x, y, z])


def test_objects_persist_over_consecutive_views(scene_dir, manifest, loaded):
  names = [v["name"] for v in manifest["views"]]
  lo, hi = default_scene.RUN_LENGTHS
  assert len(manifest["objects"]) >= default_scene.NUM_TRAIN // hi
  for obj in manifest["objects"]:
    run = [names.index(n) for n in obj["views"]]
    assert lo <= len(run) <= hi, obj
    assert run == list(range(run[0], run[0] + len(run))), obj
    description = {k: v for k, v in obj.items() if k != "views"}
    for k, view in enumerate(manifest["views"]):
      # The object is listed, at the same place, exactly in its run.
      assert (description in view["transients"]) == (k in run), (obj, k)
    inside = 0
    for k in run:
      cam = camera.camera_at(loaded.train.cameras, k)
      x = np.asarray(cam.rotation) @ _anchor(obj) + np.asarray(
          cam.translation)
      u, v = int(cam.fx * x[0] / x[2] + cam.cx), int(
          cam.fy * x[1] / x[2] + cam.cy)
      if not (0 <= u < cam.width and 0 <= v < cam.height):
        continue                          # at the edge of this view
      inside += 1
      # The same 3D object shows up in the mask where it projects, and
      # changes the image there: it stays put over its run of views.
      assert loaded.train.masks[k, v, u], (obj["id"], k)
      clean = images.read_image(os.path.join(
          scene_dir, "images", manifest["views"][k]["clean"]))
      assert np.abs(loaded.train.images[k, v, u] - clean[v, u]).max() > 0.05
    assert inside >= 1, obj


def test_loads_with_robustnerf_split(loaded, manifest):
  assert len(loaded.train) == default_scene.NUM_TRAIN
  assert len(loaded.test) == default_scene.NUM_TEST
  assert all("clutter" in n for n in loaded.train.names)
  assert all("extra" in n for n in loaded.test.names)
  assert loaded.test.masks is None
  assert loaded.train.masks.any(axis=(1, 2)).all()
  assert all(v["transients"] for v in manifest["views"])
  assert loaded.points.shape == (default_scene.NUM_TRAIN *
                                 default_scene.NUM_POINTS_PER_VIEW, 3)
  assert 0 <= loaded.point_colors.min() and loaded.point_colors.max() <= 1
  np.testing.assert_allclose(loaded.extent, 1.1 * 3.0, rtol=0.05)


def test_transient_points_are_labelled(loaded, manifest):
  # Structure from motion triangulates the objects that stay put; the
  # manifest names those rows, so benchmarks can tell them apart.
  assert manifest["num_points"] == len(loaded.points)
  rows = np.asarray(manifest["transient_points"])
  assert 0.05 < len(rows) / len(loaded.points) < 0.4
  radius = np.hypot(loaded.points[rows, 0], loaded.points[rows, 1])
  lo, hi = default_scene.TRANSIENT_RADII
  slack = 0.6                       # object size: half a crate or a balloon
  assert (radius > lo - slack).all() and (radius < hi + slack).all()
  static = np.setdiff1d(np.arange(len(loaded.points)), rows)
  # The static objects stand inside radius ~1.4 and get many points.
  near = np.hypot(loaded.points[static, 0], loaded.points[static, 1]) < 1.4
  assert near.sum() > 0.2 * len(static)


def test_clean_split(scene_dir, tmp_path):
  s = scene.load_scene(scene_dir, train_split="clean",
                       cache_dir=str(tmp_path))
  assert all("clean" in n for n in s.train.names) and s.train.masks is None


@pytest.mark.parametrize("split", ["train", "test"])
def test_cameras_look_at_the_scene_upright(loaded, split):
  views = getattr(loaded, split)
  for i in range(len(views)):
    cam = camera.camera_at(views.cameras, i)

    def project(p):
      x = np.asarray(cam.rotation) @ p + np.asarray(cam.translation)
      return (cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy)

    u, v = project(np.array([0.0, 0.0, 0.3]))
    assert abs(u - cam.width / 2) < 1 and abs(v - cam.height / 2) < 1
    # World up (+z) is up in the image (smaller row), not upside down.
    assert project(np.array([0.0, 0.0, 1.0]))[1] < v - 5
    assert camera.camera_center(cam)[2] > 0.5


def test_regenerates_when_incomplete(scene_dir, tmp_path, monkeypatch):
  # Generation itself is covered above; a copy stands in for it here.
  calls = []

  def fake_generate(folder):
    calls.append(folder)
    shutil.copytree(scene_dir, folder)

  monkeypatch.setattr(default_scene, "generate", fake_generate)
  root = str(tmp_path)
  path = default_scene.ensure_default_scene(root)
  assert len(calls) == 1
  assert os.path.basename(path) == f"default_scene_v{default_scene.VERSION}"
  manifest_file = os.path.join(path, "transients.json")
  mtime = os.stat(manifest_file).st_mtime_ns
  assert default_scene.ensure_default_scene(root) == path   # no rework
  assert os.stat(manifest_file).st_mtime_ns == mtime and len(calls) == 1
  os.remove(os.path.join(path, "images", "1extra002.png"))
  assert default_scene.ensure_default_scene(root) == path
  assert len(calls) == 2
  assert os.path.isfile(os.path.join(path, "images", "1extra002.png"))
  assert [f for f in os.listdir(root) if f.startswith(".tmp")] == []
  # A scene written by another version of the generator is rebuilt.
  with open(manifest_file) as f:
    old = json.load(f)
  old["version"] = default_scene.VERSION - 1
  with open(manifest_file, "w") as f:
    json.dump(old, f)
  assert default_scene.ensure_default_scene(root) == path
  assert len(calls) == 3
