"""Tests for the transient benchmark builder (independent mode, CLI)."""

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pycolmap
import pytest

from clipgs_jax.data import colmap
from clipgs_jax.data import transient_photos
from clipgs_jax.data import images
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.data import transients
import shared_data
from test_colmap import _pose  # pylint: disable=g-bad-import-order

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = shared_data.DATA
WIDTH, HEIGHT = 64, 48
NUM_VIEWS = 17                   # tests 0, 8, 16; 14 training views
TEST_IDX = (0, 8, 16)
NUM_TRAIN = NUM_VIEWS - len(TEST_IDX)


def _write_source(root, num=NUM_VIEWS, cam=("PINHOLE", (50.0, 51.0, 32, 24))):
  """Small COLMAP scene on a ring, random pixels; returns them by name.

  Names are deliberately unsorted in id order, to check sorting by name.
  """
  rec = pycolmap.Reconstruction()
  rec.add_camera_with_trivial_rig(pycolmap.Camera(
      camera_id=1, model=cam[0], width=WIDTH, height=HEIGHT,
      params=list(cam[1])))
  rng = np.random.default_rng(0)
  pixels = {}
  for image_id in range(1, num + 1):
    name = f"view_{(7 * image_id) % num:02d}.png"
    rot, trans = _pose(image_id, num)
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name=name, camera_id=1, image_id=image_id),
        pycolmap.Rigid3d(pycolmap.Rotation3d(rot), trans))
    path = os.path.join(root, "images", name)
    images.write_png(path, rng.random((HEIGHT, WIDTH, 3)))
    pixels[name] = images.read_image(path)      # exactly as stored
  for i in range(5):
    rec.add_point3D(np.array([i * 0.1, 0.2, -0.3]), pycolmap.Track(),
                    np.array([10 * i, 20, 30], np.uint8))
  os.makedirs(os.path.join(root, "sparse", "0"))
  rec.write_binary(os.path.join(root, "sparse", "0"))
  return pixels


def _write_photos(folder):
  """A "person" (RGBA, alpha must be dropped) and grey "clutter" photo."""
  yy, xx = np.mgrid[0:50, 0:40] / 50.0
  person = np.stack([xx, yy, 1 - xx, 0.3 * np.ones_like(xx)], -1)
  images.write_png(os.path.join(folder, "astronaut.png"), person)
  images.write_png(os.path.join(folder, "coffee.png"),
                   0.5 + 0.4 * np.sin(9 * xx[:30, :] + 5 * yy[:30, :]))
  (pathlib.Path(folder) / "notes.txt").write_text("not a photo")


@pytest.fixture(scope="module")
def source(tmp_path_factory):
  root = tmp_path_factory.mktemp("src")
  pixels = _write_source(str(root / "scene"))
  _write_photos(str(root / "photos"))
  return {"root": root, "scene": str(root / "scene"),
          "photos": str(root / "photos"), "pixels": pixels}


def _build(source, out, **kwargs):
  kwargs.setdefault("seed", 3)
  return transients.build(source["scene"], source["photos"], str(out), **kwargs)


@pytest.fixture(scope="module")
def half(source):
  out = source["root"] / "half"
  return out, _build(source, out, fraction=0.5)


@pytest.fixture(scope="module")
def full(source):
  out = source["root"] / "full"
  return out, _build(source, out, fraction=1.0)


def _read(path):
  return images.read_image(str(path))


def _dilate(mask, radius):
  out = mask.copy()
  for dy in range(-radius, radius + 1):
    for dx in range(-radius, radius + 1):
      out |= np.roll(np.roll(mask, dy, 0), dx, 1)
  return out


def test_layout_and_pixels(source, half):
  out, manifest = half
  names = sorted(source["pixels"])
  files = sorted(os.listdir(out / "images"))
  assert files == sorted([f"0clean{k:03d}.png" for k in range(NUM_TRAIN)] +
                         [f"1extra{k:03d}.png" for k in range(3)] +
                         [f"2clutter{k:03d}.png" for k in range(NUM_TRAIN)])
  assert sorted(os.listdir(out / "masks")) == [
      f"2clutter{k:03d}.png" for k in range(NUM_TRAIN)]
  assert sorted(os.listdir(out)) == ["images", "masks", "sparse",
                                     "transients.json"]
  assert not [p for p in os.listdir(out.parent) if ".tmp-" in p]
  # Every 8th source view by sorted name is an unmodified test view.
  assert [t["source"] for t in manifest["tests"]] == [names[i]
                                                      for i in TEST_IDX]
  for t in manifest["tests"]:
    np.testing.assert_array_equal(_read(out / "images" / t["name"]),
                                  source["pixels"][t["source"]])
  # Half of the 14 training views are cluttered, each with 1-3 photos.
  cluttered = [v for v in manifest["views"] if v["transients"]]
  assert manifest["num_cluttered"] == len(cluttered) == NUM_TRAIN // 2
  assert all(1 <= len(v["transients"]) <= 3 for v in cluttered)
  assert [v["source"] for v in manifest["views"]] == [
      n for i, n in enumerate(names) if i not in TEST_IDX]
  for v in manifest["views"]:
    src = source["pixels"][v["source"]]
    clean, image = _read(out / "images" / v["clean"]), _read(
        out / "images" / v["name"])
    mask = _read(out / v["mask"])[..., 0] > 0.5
    np.testing.assert_array_equal(clean, src)
    assert v["mask_pixels"] == mask.sum()
    changed = np.any(image != src, axis=-1)
    if not v["transients"]:
      assert not mask.any() and not changed.any(), v["name"]
      continue
    assert mask.any()
    # The mask is what changed, up to the soft edge (feather 1.5 pixels).
    assert (mask & changed).sum() >= 0.97 * mask.sum(), v["name"]
    assert not (changed & ~_dilate(mask, 2)).any(), v["name"]
    boxes = np.zeros_like(mask)
    for t in v["transients"]:
      assert t["photo"] in ("astronaut.png", "coffee.png")
      assert t["category"] == {"astronaut.png": "person",
                               "coffee.png": "clutter"}[t["photo"]]
      assert t["shape"] in ("ellipse", "rounded_rect")
      x0, y0, x1, y1 = t["box"]
      assert 0 <= x0 < x1 <= WIDTH and 0 <= y0 < y1 <= HEIGHT
      # 15-45 % of the height (up to 20 % may hang over the border).
      assert y1 - y0 <= round(0.45 * HEIGHT)
      boxes[y0:y1, x0:x1] = True
    assert not (changed & ~boxes).any()
  counts = manifest["transients_by_category"]
  assert sum(counts.values()) == sum(len(v["transients"])
                                     for v in manifest["views"])
  assert manifest["per_view"] == [1, 3] and manifest["fraction"] == 0.5


def test_sparse_model(source, half):
  out, manifest = half
  rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
  src = pycolmap.Reconstruction(os.path.join(source["scene"], "sparse", "0"))
  assert {im.name for im in rec.images.values()} == set(
      os.listdir(out / "images"))
  assert rec.num_points3D() == src.num_points3D()
  assert {c.model.name for c in rec.cameras.values()} == {"PINHOLE"}
  by_name = {im.name: im for im in rec.images.values()}
  src_by_name = {im.name: im for im in src.images.values()}
  for v in manifest["views"] + manifest["tests"]:
    want = src_by_name[v["source"]].cam_from_world().matrix()
    for name in (v["name"], v.get("clean", v["name"])):
      np.testing.assert_allclose(by_name[name].cam_from_world().matrix(),
                                 want, atol=1e-12)
  np.testing.assert_allclose(rec.cameras[1].params, [50, 51, 32, 24])


def test_load_scene_splits(source, half, tmp_path):
  out, manifest = half
  clutter = scene_lib.load_scene(str(out), cache_dir=str(tmp_path / "c"))
  assert len(clutter.train) == NUM_TRAIN and len(clutter.test) == 3
  assert all(n.startswith("2clutter") for n in clutter.train.names)
  assert all(n.startswith("1extra") for n in clutter.test.names)
  assert clutter.train.masks.shape == (NUM_TRAIN, HEIGHT, WIDTH)
  np.testing.assert_array_equal(
      clutter.train.masks.sum(axis=(1, 2)),
      [v["mask_pixels"] for v in manifest["views"]])
  clean = scene_lib.load_scene(str(out), train_split="clean",
                               cache_dir=str(tmp_path / "c"))
  assert all(n.startswith("0clean") for n in clean.train.names)
  assert clean.train.masks is None
  np.testing.assert_array_equal(
      clean.train.images,
      np.stack([source["pixels"][v["source"]] for v in manifest["views"]]))
  np.testing.assert_array_equal(clean.train.cameras.rotation,
                                clutter.train.cameras.rotation)
  np.testing.assert_array_equal(clean.train.cameras.translation,
                                clutter.train.cameras.translation)


def test_fraction_one_is_a_superset(half, full):
  (out_h, man_h), (out_f, man_f) = half, full
  assert man_f["num_cluttered"] == NUM_TRAIN
  for vh, vf in zip(man_h["views"], man_f["views"]):
    if vh["transients"]:
      # Placements depend on (seed, view) only: the same in both builds.
      assert vh["transients"] == vf["transients"]
      assert (out_h / "images" / vh["name"]).read_bytes() == (
          out_f / "images" / vf["name"]).read_bytes()


def test_deterministic_for_a_seed(source, half, tmp_path):
  out, _ = half
  again = tmp_path / "again"
  _build(source, again, fraction=0.5)
  for rel in ["transients.json", "sparse/0/images.bin"] + [
      f"images/{f}" for f in sorted(os.listdir(out / "images"))]:
    assert (out / rel).read_bytes() == (again / rel).read_bytes(), rel
  other = _build(source, tmp_path / "other", fraction=0.5, seed=4)
  assert other["views"] != json.loads(
      (out / "transients.json").read_text())["views"]


def test_overwrite(source, tmp_path):
  out = tmp_path / "o"
  out.mkdir()
  (out / "stale.txt").write_text("x")
  with pytest.raises(ValueError, match="--overwrite"):
    _build(source, out, fraction=0.0)
  manifest = _build(source, out, fraction=0.0, per_view="2", overwrite=True)
  assert manifest["num_cluttered"] == 0 and not (out / "stale.txt").exists()
  assert sorted(os.listdir(tmp_path)) == ["o"]   # no temp or old folders


@pytest.mark.parametrize("kwargs,needle", [
    ({"scene": "missing"}, "--clean_scene"),
    ({"scene": "empty"}, "--clean_scene"),
    ({"photos": "missing"}, "--distractors"),
    ({"photos": "empty"}, "--distractors"),
    ({"photos": "unknown"}, "dog.png"),
    ({"fraction": 1.5}, "--fraction"),
    ({"fraction": -0.1}, "--fraction"),
    ({"per_view": "0"}, "--per_view"),
    ({"per_view": "3..1"}, "--per_view"),
    ({"per_view": "a..b"}, "--per_view"),
    ({"seed": -1}, "--seed"),
])
def test_bad_input(source, tmp_path, kwargs, needle):
  (tmp_path / "empty").mkdir()
  (tmp_path / "unknown").mkdir()
  images.write_png(str(tmp_path / "unknown" / "dog.png"),
                   np.zeros((4, 4, 3)))
  paths = {"missing": str(tmp_path / "nope"), "empty": str(tmp_path / "empty"),
           "unknown": str(tmp_path / "unknown")}
  scene = paths.get(kwargs.pop("scene", None), source["scene"])
  photos = paths.get(kwargs.pop("photos", None), source["photos"])
  kwargs.setdefault("seed", 0)
  with pytest.raises((ValueError, FileNotFoundError)) as e:
    transients.build(scene, photos, str(tmp_path / "out"), **kwargs)
  assert "\n" not in str(e.value) and needle in str(e.value), str(e.value)
  assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("text,want", [("1..3", (1, 3)), ("2", (2, 2)),
                                       (" 2..2 ", (2, 2))])
def test_parse_per_view(text, want):
  assert transients.parse_per_view(text) == want


@pytest.mark.parametrize("shape", ["ellipse", "rounded_rect"])
def test_shape_alpha(shape):
  alpha = transient_photos.shape_alpha(60, 40, shape)
  assert alpha.shape == (40, 60) and alpha.dtype == np.float32
  assert alpha[20, 30] == 1 and alpha[0, 0] == 0
  # Zero on the box border, symmetric, soft: some values strictly between.
  assert alpha[[0, -1]].max() == 0 and alpha[:, [0, -1]].max() == 0
  np.testing.assert_array_equal(alpha, alpha[::-1, ::-1])
  assert ((alpha > 0) & (alpha < 1)).sum() > 100
  # The 0.5 outline is inset by feather / 2 + 0.5 = 1.25 px (feather 1.5):
  # semi-axes 28.75 and 18.75, area pi a b = 1693 px.
  if shape == "ellipse":
    assert abs((alpha > 0.5).sum() - np.pi * 28.75 * 18.75) < 40


def test_distorted_source_uses_undistorted_frame(tmp_path):
  pixels = _write_source(str(tmp_path / "s"), num=9,
                         cam=("SIMPLE_RADIAL", (50.0, 32, 24, -0.2)))
  del pixels
  _write_photos(str(tmp_path / "p"))
  cache = str(tmp_path / "cache")
  manifest = transients.build(str(tmp_path / "s"), str(tmp_path / "p"),
                         str(tmp_path / "out"), seed=0, fraction=1.0,
                         cache_dir=cache)
  assert manifest["undistorted"] and manifest["num_train"] == 7
  model = colmap.load_model(str(tmp_path / "s"), cache_dir=cache)
  rec = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
  cam = rec.cameras[1]
  assert cam.model.name == "PINHOLE"
  np.testing.assert_allclose(cam.params, model.intrinsics[0])
  assert (cam.width, cam.height) == tuple(model.sizes[0])
  for v in manifest["views"]:
    np.testing.assert_array_equal(
        _read(tmp_path / "out" / "images" / v["clean"]),
        _read(os.path.join(model.image_dir, v["source"])))
    assert _read(tmp_path / "out" / v["mask"]).shape[1::-1] == tuple(
        model.sizes[0])
  out = scene_lib.load_scene(str(tmp_path / "out"), cache_dir=cache)
  assert len(out.train) == 7 and out.train.masks.any(axis=(1, 2)).all()


def test_cli(source, tmp_path):
  out = tmp_path / "cli"
  cmd = [sys.executable, str(ROOT / "experiments" / "prepare.py"),
         "--prepare=benchmark", f"--clean_scene={source['scene']}",
         f"--distractors={source['photos']}",
         f"--out={out}", "--seed=1", "--fraction=1", "--per_view=1..2"]
  env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
  run = subprocess.run(cmd, env=env, capture_output=True, text=True,
                       check=False, timeout=120)
  assert run.returncode == 0, run.stderr
  assert f"{NUM_TRAIN} cluttered" in run.stdout
  assert "(independent)" in run.stdout
  manifest = json.loads((out / "transients.json").read_text())
  assert manifest["per_view"] == [1, 2] and manifest["seed"] == 1


@shared_data.needs_data("distractors")
def test_real_distractors(source, tmp_path):
  photos = transient_photos.list_photos(str(DATA / "distractors"))
  by_name = {os.path.basename(p): c for p, c in photos}
  assert len(photos) == 8 and sorted(by_name.values()).count("person") == 5
  manifest = transients.build(source["scene"], str(DATA / "distractors"),
                         str(tmp_path / "real"), seed=0, fraction=1.0)
  assert manifest["num_cluttered"] == NUM_TRAIN
  for v in manifest["views"]:
    for t in v["transients"]:
      assert t["category"] == by_name[t["photo"]]


def test_cli_error_is_one_line(source, tmp_path):
  """A photo without a category: exit 1, one stderr line naming it, no
  output folder and no help text."""
  (tmp_path / "photos").mkdir()
  images.write_png(str(tmp_path / "photos" / "dog.png"), np.zeros((4, 4, 3)))
  out = tmp_path / "cli"
  cmd = [sys.executable, str(ROOT / "experiments" / "prepare.py"),
         "--prepare=benchmark", f"--clean_scene={source['scene']}",
         f"--distractors={tmp_path / 'photos'}",
         f"--out={out}", "--seed=1"]
  env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
  run = subprocess.run(cmd, env=env, capture_output=True, text=True,
                       check=False, timeout=120)
  assert run.returncode == 1
  lines = run.stderr.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith("error: "), run.stderr
  assert str(tmp_path / "photos" / "dog.png") in lines[0]
  assert not out.exists()
