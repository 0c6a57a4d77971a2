"""Tests for data/scene.py: splits, downscaling, masks and real scenes."""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pycolmap
import pytest

from clipgs_jax import camera
from clipgs_jax.data import colmap
from clipgs_jax.data import images
from clipgs_jax.data import scene
import shared_data  # tests/, on sys.path under pytest

DATA = shared_data.DATA
needs_data = shared_data.needs_data("bird", "bonsai")


def write_scene(root, names, cams=((65, 49),), cam_of=None, image_sizes=None,
                radius=2.0):
  """Small PINHOLE scene on a ring of `radius` around (1, 2, 3).

  Returns the image arrays by name.
  """
  rec = pycolmap.Reconstruction()
  for cam_id, (w, h) in enumerate(cams, 1):
    rec.add_camera_with_trivial_rig(pycolmap.Camera(
        camera_id=cam_id, model="PINHOLE", width=w, height=h,
        params=[40.0, 41.0, w / 2, h / 2]))
  rng = np.random.default_rng(0)
  pixels = {}
  for image_id, name in enumerate(names, 1):
    az = 2 * np.pi * image_id / len(names)
    eye = np.array([1, 2, 3]) + radius * np.array([np.cos(az), np.sin(az), 0])
    z = np.array([1, 2, 3]) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0, 0, 1.0])
    rot = np.stack([x, np.cross(z, x), z])
    cam_id = 1 if cam_of is None else cam_of[name]
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name=name, camera_id=cam_id, image_id=image_id),
        pycolmap.Rigid3d(pycolmap.Rotation3d(rot), -rot @ eye))
    w, h = (image_sizes or {}).get(name, cams[cam_id - 1])
    pixels[name] = np.round(rng.random((h, w, 3)) * 255) / 255
    images.write_png(os.path.join(root, "images", name), pixels[name])
  rec.add_point3D(np.array([0.5, 0.5, 0.5]), pycolmap.Track(),
                  np.array([255, 0, 51], np.uint8))
  os.makedirs(os.path.join(root, "sparse", "0"))
  rec.write_binary(os.path.join(root, "sparse", "0"))
  return pixels


def _load(root, **kwargs):
  kwargs.setdefault("cache_dir", os.path.join(root, "..", "cache"))
  return scene.load_scene(str(root), **kwargs)


def test_every_eighth_split(tmp_path):
  names = [f"img{i:02d}.png" for i in range(18)]
  pixels = write_scene(tmp_path / "s", names)
  s = _load(tmp_path / "s")
  assert s.test.names == ("img00.png", "img08.png", "img16.png")
  assert len(s.train) == 15 and "img08.png" not in s.train.names
  assert s.train.images.shape == (15, 49, 65, 3)
  assert s.train.images.dtype == np.float32
  np.testing.assert_allclose(s.test.images[1], pixels["img08.png"], atol=1e-6)
  assert s.train.masks is None and s.test.masks is None
  np.testing.assert_allclose(s.points, [[0.5, 0.5, 0.5]])
  np.testing.assert_allclose(s.point_colors, [[1.0, 0.0, 0.2]])
  assert s.point_colors.dtype == np.float32
  # 3DGS's cameras_extent: 1.1 x the largest distance of a training camera
  # centre from the mean centre (centres lie on a radius-2 circle).
  centres = np.stack([camera.camera_center(camera.camera_at(s.train.cameras, i))
                      for i in range(15)])
  np.testing.assert_allclose(np.linalg.norm(centres - [1, 2, 3], axis=1), 2,
                             rtol=1e-5)
  radius = np.linalg.norm(centres - centres.mean(0), axis=1).max()
  np.testing.assert_allclose(s.extent, 1.1 * radius, rtol=1e-5)
  assert 2.0 < radius < 2.2       # mean is off-centre: 3 views are held out
  assert s.train.cameras.rotation.shape == (15, 3, 3)
  assert s.train.cameras.fx.shape == (15,)
  assert (s.train.cameras.width, s.train.cameras.height) == (65, 49)


def test_robustnerf_split(tmp_path):
  names = ([f"0clean{i:03d}.png" for i in range(3)] +
           [f"1extra{i:03d}.png" for i in range(2)] +
           [f"2clutter{i:03d}.png" for i in range(4)])
  write_scene(tmp_path / "s", names)
  s = _load(tmp_path / "s")
  assert s.test.names == ("1extra000.png", "1extra001.png")
  assert s.train.names == tuple(f"2clutter{i:03d}.png" for i in range(4))
  clean = _load(tmp_path / "s", train_split="clean")
  assert clean.train.names == tuple(f"0clean{i:03d}.png" for i in range(3))
  assert clean.test.names == s.test.names
  with pytest.raises(ValueError, match="train_split"):
    _load(tmp_path / "s", train_split="extra")


def test_no_test_views(tmp_path):
  write_scene(tmp_path / "s", ["2clutter000.png", "2clutter001.png"])
  with pytest.raises(ValueError) as e:
    _load(tmp_path / "s")
  msg = str(e.value)
  assert "no test views" in msg and "extra" in msg and "\n" not in msg
  assert os.path.join("s", "sparse", "0") in msg


def test_single_image_has_no_training_views(tmp_path):
  write_scene(tmp_path / "s", ["a.png"])
  with pytest.raises(ValueError, match="no training views"):
    _load(tmp_path / "s")


def test_ambiguous_robustnerf_name(tmp_path):
  write_scene(tmp_path / "s", ["1extra0.png", "2clutter0.png", "other.png"])
  with pytest.raises(ValueError, match="other.png"):
    _load(tmp_path / "s")


def test_mixed_sizes_share_a_canvas(tmp_path):
  names = [f"img{i:02d}.png" for i in range(4)]
  pixels = write_scene(tmp_path / "s", names, cams=((64, 48), (80, 40)),
                       cam_of={n: 1 if n != "img02.png" else 2
                               for n in names})
  s = _load(tmp_path / "s")
  # img00 is a test view (every 8th); the training views share an 80x48
  # canvas, each photo in its top-left corner.
  assert (s.train.cameras.width, s.train.cameras.height) == (80, 48)
  np.testing.assert_array_equal(s.train.sizes, [[64, 48], [80, 40],
                                                [64, 48]])
  assert s.train.images.shape == (3, 48, 80, 3)
  np.testing.assert_allclose(s.train.images[1, :40], pixels["img02.png"],
                             atol=1e-6)
  np.testing.assert_array_equal(s.train.images[1, 40:], 0.0)
  np.testing.assert_allclose(s.train.images[0, :, :64],
                             pixels["img01.png"], atol=1e-6)
  np.testing.assert_array_equal(s.train.images[0, :, 64:], 0.0)
  assert s.test.sizes is None and s.test.images.shape == (1, 48, 64, 3)
  # Packed and read back with its sizes.
  scene.pack(str(tmp_path / "s"), str(tmp_path / "s.npz"), 1,
             cache_dir=str(tmp_path / "cache"))
  packed = scene.load_scene(str(tmp_path / "s.npz"))
  np.testing.assert_array_equal(packed.train.sizes, s.train.sizes)
  _assert_same_scene(packed, s)


def test_a_canvas_too_large_for_its_photos_is_refused(tmp_path):
  names = [f"img{i:02d}.png" for i in range(9)]
  write_scene(tmp_path / "s", names, cams=((64, 48), (16, 12)),
              cam_of={n: 1 if n == "img01.png" else 2 for n in names})
  with pytest.raises(ValueError) as e:
    _load(tmp_path / "s")
  assert "16x12 to 64x48" in str(e.value) and "\n" not in str(e.value)


def test_a_process_reads_only_its_views(tmp_path):
  names = [f"img{i:02d}.png" for i in range(9)]
  write_scene(tmp_path / "s", names)
  full = _load(tmp_path / "s")
  held = _load(tmp_path / "s", train_views=lambda v: v % 2 == 1)
  assert held.train.names == full.train.names[1::2]
  np.testing.assert_array_equal(held.train.ids, [1, 3, 5])
  np.testing.assert_array_equal(held.train.images, full.train.images[1::2])
  assert held.extent == full.extent
  np.testing.assert_array_equal(held.train_cameras.rotation,
                                full.train.cameras.rotation)
  np.testing.assert_array_equal(held.train_cameras.translation,
                                full.train.cameras.translation)


def test_image_size_disagrees_with_camera(tmp_path):
  write_scene(tmp_path / "s", ["a.png", "b.png"],
              image_sizes={"b.png": (60, 49)})
  for factor in (1, 2):
    with pytest.raises(ValueError) as e:
      _load(tmp_path / "s", downscale=factor)
    assert str(tmp_path / "s" / "images" / "b.png") in str(e.value)


def test_missing_image(tmp_path):
  write_scene(tmp_path / "s", ["a.png", "b.png"])
  os.remove(tmp_path / "s" / "images" / "a.png")
  with pytest.raises(FileNotFoundError, match="a.png"):
    _load(tmp_path / "s")


def test_downscale_non_divisible(tmp_path):
  names = [f"img{i}.png" for i in range(3)]
  pixels = write_scene(tmp_path / "s", names)                  # 65 x 49
  s = _load(tmp_path / "s", downscale=2)
  # round(32.5) = 33, round(24.5) = 25; intrinsics scale by 33/65, 25/49.
  assert s.train.images.shape == (2, 25, 33, 3)
  cams = s.train.cameras
  np.testing.assert_allclose(cams.fx, 40.0 * 33 / 65, rtol=1e-6)
  np.testing.assert_allclose(cams.fy, 41.0 * 25 / 49, rtol=1e-6)
  np.testing.assert_allclose(cams.cx, 32.5 * 33 / 65, rtol=1e-6)  # = 16.5
  np.testing.assert_allclose(cams.cy, 24.5 * 25 / 49, rtol=1e-6)  # = 12.5
  np.testing.assert_allclose(
      s.train.images[0], images.resize_area(pixels["img1.png"], 33, 25),
      atol=2e-5)
  # The principal point stays at the image centre under the +0.5
  # convention: cx / width is unchanged.
  np.testing.assert_allclose(cams.cx / 33, 32.5 / 65, rtol=1e-6)
  with pytest.raises(ValueError, match="downscale factor"):
    _load(tmp_path / "s", downscale=0)


def test_prescaled_folder_is_used(tmp_path):
  names = ["a.png", "b.png"]
  write_scene(tmp_path / "s", names, cams=((64, 48),))
  for name in names:
    images.write_png(str(tmp_path / "s" / "images_4" / name),
                     np.full((12, 16, 3), 0.25))
  s = _load(tmp_path / "s", downscale=4)
  np.testing.assert_allclose(s.train.images, 64 / 255, atol=1e-6)
  np.testing.assert_allclose(s.train.cameras.fx, 10.0)
  os.remove(tmp_path / "s" / "images_4" / "a.png")
  with pytest.raises(FileNotFoundError, match="images_4"):
    _load(tmp_path / "s", downscale=4)


def test_masks(tmp_path):
  names = ["1extra0.png"] + [f"2clutter{i}.png" for i in range(3)]
  write_scene(tmp_path / "s", names, cams=((64, 48),))
  masks = np.zeros((3, 48, 64), np.float32)
  masks[0, 10:20, 30:40] = 1.0
  masks[1, 11, 31] = 1.0       # one full-resolution pixel of a 2x2 block
  masks[1, 30:32, 40:42] = 0.4  # grey under MASK_THRESHOLD: not transient
  masks[2, :, :3] = 1.0
  for i in range(3):
    images.write_png(str(tmp_path / "s" / "masks" / f"2clutter{i}.png"),
                     masks[i])
  s = _load(tmp_path / "s")
  np.testing.assert_array_equal(s.train.masks, masks >= scene.MASK_THRESHOLD)
  assert s.test.masks is None
  small = _load(tmp_path / "s", downscale=2)
  assert small.train.masks.shape == (3, 24, 32)
  # A downscaled pixel is transient where any of its 2x2 source pixels is:
  # block column 0 (source columns 0-1, both masked) and block column 1
  # (source columns 2-3, column 2 masked), not block column 2 (4-5)...
  np.testing.assert_array_equal(small.train.masks[2, 0, :3],
                                [True, True, False])
  # ... and the block holding the single masked pixel (a quarter of it).
  assert small.train.masks[1].sum() == 1 and small.train.masks[1, 5, 15]
  assert small.train.masks[0].sum() == 25
  os.remove(tmp_path / "s" / "masks" / "2clutter1.png")
  with pytest.raises(FileNotFoundError, match="2clutter1.png"):
    _load(tmp_path / "s")


def test_mask_of_the_wrong_size(tmp_path):
  names = ["1extra0.png", "2clutter0.png"]
  write_scene(tmp_path / "s", names, cams=((64, 48),))
  images.write_png(str(tmp_path / "s" / "masks" / "2clutter0.png"),
                   np.zeros((24, 32), bool))
  with pytest.raises(ValueError, match="2clutter0.png is 32x24 pixels"):
    _load(tmp_path / "s", downscale=2)


def test_camera_at(tmp_path):
  write_scene(tmp_path / "s", [f"img{i}.png" for i in range(4)])
  cams = _load(tmp_path / "s").train.cameras
  one = camera.camera_at(cams, 1)
  camera.validate(one)
  np.testing.assert_array_equal(one.rotation, cams.rotation[1])
  np.testing.assert_array_equal(one.fx, cams.fx[1])

  @jax.jit
  def centre(cams, i):
    return camera.camera_center(camera.camera_at(cams, i), xnp=jnp)

  for i in range(3):
    np.testing.assert_allclose(centre(cams, jnp.int32(i)),
                               camera.camera_center(camera.camera_at(cams, i)),
                               atol=1e-5)


@pytest.fixture(scope="module")
def real_cache(tmp_path_factory):
  # Shared by the real-data tests so bonsai is undistorted once.
  return str(tmp_path_factory.getbasetemp() / "real-data-cache")


@needs_data
def test_bird_downscale_4(real_cache):
  path = str(DATA / "bird")
  cache = os.path.join(real_cache, "bird")
  s = scene.load_scene(path, downscale=4, cache_dir=cache)
  model = colmap.load_model(path)
  assert s.train.images.shape == (161, 240, 136, 3)
  assert s.test.images.shape == (23, 240, 136, 3)
  assert s.test.names == model.names[::8]
  assert set(s.train.names) | set(s.test.names) == set(model.names)
  assert (s.train.cameras.width, s.train.cameras.height) == (136, 240)
  idx = [model.names.index(n) for n in s.train.names]
  np.testing.assert_allclose(s.train.cameras.fx, model.intrinsics[idx, 0] / 4,
                             rtol=1e-6)
  np.testing.assert_allclose(s.train.cameras.cx, 272 / 4)
  np.testing.assert_allclose(s.train.cameras.cy, 480 / 4)
  assert 0 <= s.train.images.min() and s.train.images.max() <= 1
  assert s.train.masks is None and s.points.shape[1] == 3
  assert s.extent > 0
  # The second load is served from the resize cache, identically.
  again = scene.load_scene(path, downscale=4, cache_dir=cache)
  np.testing.assert_array_equal(again.test.images, s.test.images)


@needs_data
def test_bonsai_is_undistorted(real_cache):
  path = str(DATA / "bonsai")
  cache = os.path.join(real_cache, "bonsai")
  s = scene.load_scene(path, downscale=4, cache_dir=cache)
  model = colmap.load_model(path, cache_dir=cache)
  assert model.undistorted and model.image_dir.startswith(cache)
  raw = pycolmap.Reconstruction(str(DATA / "bonsai" / "sparse" / "0"))
  assert {c.model.name for c in raw.cameras.values()} == {"SIMPLE_RADIAL"}
  w, h = model.sizes[0]
  sw, sh = images.downscaled_size(w, h, 4)
  assert s.train.images.shape[1:] == (sh, sw, 3)
  assert len(s.train) + len(s.test) == 98 and len(s.test) == 13
  np.testing.assert_allclose(s.train.cameras.fx,
                             model.intrinsics[0, 0] * sw / w, rtol=1e-6)
  np.testing.assert_allclose(s.train.cameras.cx,
                             model.intrinsics[0, 2] * sw / w, rtol=1e-6)


def _assert_same_views(a: scene.Views, b: scene.Views):
  assert a.names == b.names
  assert (a.sizes is None) == (b.sizes is None)
  if a.sizes is not None:
    np.testing.assert_array_equal(a.sizes, b.sizes)
  assert a.images.dtype == b.images.dtype == np.float32
  np.testing.assert_array_equal(a.images, b.images)
  assert (a.masks is None) == (b.masks is None)
  if a.masks is not None:
    np.testing.assert_array_equal(a.masks, b.masks)
  assert (a.cameras.width, a.cameras.height) == (b.cameras.width,
                                                 b.cameras.height)
  for field in ("rotation", "translation", "fx", "fy", "cx", "cy"):
    x, y = getattr(a.cameras, field), getattr(b.cameras, field)
    assert x.dtype == y.dtype, field
    np.testing.assert_array_equal(x, y, err_msg=field)


def _assert_same_scene(a: scene.Scene, b: scene.Scene):
  _assert_same_views(a.train, b.train)
  _assert_same_views(a.test, b.test)
  np.testing.assert_array_equal(a.points, b.points)
  np.testing.assert_array_equal(a.point_colors, b.point_colors)
  assert a.extent == b.extent


def _robustnerf_scene(root, clean: bool):
  """1 extra, 3 clutter views with masks (and their 3 clean twins)."""
  names = (["1extra0.png"] + [f"2clutter{i}.png" for i in range(3)] +
           ([f"3clean{i}.png" for i in range(3)] if clean else []))
  write_scene(root, names, cams=((64, 48),))
  for i in range(3):
    mask = np.zeros((48, 64), bool)
    mask[5 * i:5 * i + 9, 10:30] = True
    images.write_png(str(root / "masks" / f"2clutter{i}.png"), mask)


def test_pack_is_the_loaded_scene_bit_for_bit(tmp_path, monkeypatch):
  _robustnerf_scene(tmp_path / "s", clean=True)
  cache = str(tmp_path / "cache")
  out = str(tmp_path / "s.npz")
  reads = []
  load_model = colmap.load_model
  monkeypatch.setattr(colmap, "load_model",
                      lambda *a, **k: reads.append(a) or load_model(*a, **k))
  assert scene.pack(str(tmp_path / "s"), out, 2, cache_dir=cache) == (
      "clutter", "clean")
  assert len(reads) == 1        # both splits from one read of the model
  monkeypatch.undo()
  for split in ("clutter", "clean"):
    packed = scene.load_scene(out, downscale=2, train_split=split)
    _assert_same_scene(_load(tmp_path / "s", downscale=2, train_split=split),
                       packed)
    assert packed.path == out
  assert packed.train.masks is None            # the clean twins have none
  # Without RobustNeRF names train_split is ignored, as for the folder.
  write_scene(tmp_path / "plain", [f"v{i:02d}.png" for i in range(10)])
  out = str(tmp_path / "plain.npz")
  assert scene.pack(str(tmp_path / "plain"), out, 1, cache_dir=cache) == ()
  for split in ("clutter", "clean"):
    _assert_same_scene(_load(tmp_path / "plain", train_split=split),
                       scene.load_scene(out, train_split=split))


def test_pack_errors_name_the_file_and_the_fix(tmp_path):
  _robustnerf_scene(tmp_path / "s", clean=False)
  out = str(tmp_path / "s.npz")
  scene.pack(str(tmp_path / "s"), out, 2, cache_dir=str(tmp_path / "c"))
  with pytest.raises(ValueError, match=r"holds downscale 2, not 1; pass "
                     r"--config.data.downscale=2"):
    scene.load_scene(out, downscale=1)
  with pytest.raises(ValueError, match=r"split\(s\) \('clutter',\), not "
                     "'clean'"):
    scene.load_scene(out, downscale=2, train_split="clean")
  with pytest.raises(ValueError, match="must end in .npz"):
    scene.pack(str(tmp_path / "s"), str(tmp_path / "s.zip"), 2)
  with pytest.raises(FileNotFoundError, match="prepare.py --prepare=pack"):
    scene.load_scene(str(tmp_path / "missing.npz"))
  np.savez(tmp_path / "other.npz", x=np.zeros(3))
  with pytest.raises(ValueError, match="other.npz is not a scene pack"):
    scene.load_scene(str(tmp_path / "other.npz"))
  (tmp_path / "junk.npz").write_bytes(b"not a zip file")
  with pytest.raises(ValueError, match="junk.npz cannot be read as a scene"):
    scene.load_scene(str(tmp_path / "junk.npz"))


def test_pack_trains_without_pycolmap(tmp_path):
  """The package imports, and a pack loads, where pycolmap is missing."""
  _robustnerf_scene(tmp_path / "s", clean=False)
  out = str(tmp_path / "s.npz")
  scene.pack(str(tmp_path / "s"), out, 2, cache_dir=str(tmp_path / "c"))
  code = f"""
import sys
sys.modules["pycolmap"] = None           # import pycolmap raises ImportError
from clipgs_jax import run
from clipgs_jax.lab import sweep
from clipgs_jax.data import scene
s = scene.load_scene({out!r}, downscale=2)
print(s.train.images.shape, int(s.train.masks.sum()))
try:
  scene.load_scene({str(tmp_path / "s")!r})
except ImportError:
  print("folder needs pycolmap")
"""
  env = dict(os.environ, JAX_PLATFORMS="cpu")
  proc = subprocess.run([sys.executable, "-c", code], capture_output=True,
                        text=True, env=env, check=False, timeout=300)
  assert proc.returncode == 0, proc.stderr
  masked = int(_load(tmp_path / "s", downscale=2).train.masks.sum())
  assert proc.stdout.split("\n")[:2] == [f"(3, 24, 32, 3) {masked}",
                                         "folder needs pycolmap"]
