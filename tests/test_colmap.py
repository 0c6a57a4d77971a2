"""Tests for data/colmap.py: reading, undistortion and bad-input errors."""

import os
import shutil
import struct

import numpy as np
import pycolmap
import pytest

from clipgs_jax.data import colmap
from clipgs_jax.data import images
import shared_data  # tests/, on sys.path under pytest

DATA = shared_data.DATA
needs_data = shared_data.needs_data("bird")


def _pose(k, n):
  """World-to-camera (R, t) of a camera on a ring looking at the origin."""
  az = 2 * np.pi * k / n
  eye = np.array([3 * np.cos(az), 3 * np.sin(az), 1.0])
  z = -eye / np.linalg.norm(eye)
  x = np.cross(z, [0, 0, 1.0])
  x /= np.linalg.norm(x)
  rot = np.stack([x, np.cross(z, x), z])
  return rot, -rot @ eye


def write_scene(root, names, cams=(("PINHOLE", 64, 48, (50, 50, 32, 24)),),
                cam_of=None, text=False, image_sizes=None):
  """Writes a small COLMAP scene; returns the expected (R, t) per name."""
  rec = pycolmap.Reconstruction()
  for cam_id, (model, w, h, params) in enumerate(cams, 1):
    rec.add_camera_with_trivial_rig(pycolmap.Camera(
        camera_id=cam_id, model=model, width=w, height=h, params=list(params)))
  rng = np.random.default_rng(0)
  poses = {}
  for image_id, name in enumerate(names, 1):
    cam_id = 1 if cam_of is None else cam_of[name]
    rot, t = _pose(image_id, len(names))
    poses[name] = (rot, t)
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name=name, camera_id=cam_id, image_id=image_id),
        pycolmap.Rigid3d(pycolmap.Rotation3d(rot), t))
    _, w, h, _ = cams[cam_id - 1]
    if image_sizes and name in image_sizes:
      w, h = image_sizes[name]
    images.write_png(os.path.join(root, "images", name),
                     rng.random((h, w, 3)))
  for i in range(10):
    rec.add_point3D(np.array([i * 0.1, -i * 0.2, 0.5]), pycolmap.Track(),
                    np.array([i, 2 * i, 3 * i], np.uint8))
  sparse = os.path.join(root, "sparse", "0")
  os.makedirs(sparse)
  if text:
    rec.write_text(sparse)
  else:
    rec.write_binary(sparse)
  return poses


def _ring_poses(n, inward=True):
  """World-to-camera (R [n, 3, 3], t [n, 3]) of a ring looking at the
  origin, or away from it (a folded orbit) when not `inward`."""
  poses = [_pose(k, n) for k in range(n)]
  rot = np.stack([r for r, _ in poses])
  if not inward:  # turn each camera around its y axis: x and z flip
    rot = rot * np.array([-1.0, 1.0, -1.0])[None, :, None]
  eyes = np.stack([-r.T @ t for r, t in poses])
  return rot, -np.einsum("nij,nj->ni", rot, eyes)


def test_facing_fraction_tells_orbit_from_folded():
  for inward, share in ((True, 1.0), (False, 0.0)):
    centers, axes = colmap.centers_and_axes(*_ring_poses(12, inward))
    assert colmap.facing_fraction(centers, axes) == share


def test_fold_warning_names_the_model_and_the_fix():
  assert colmap.fold_warning(*_ring_poses(12), "m") is None
  warning = colmap.fold_warning(*_ring_poses(12, inward=False), "m/sparse/0")
  assert warning.startswith("m/sparse/0: 0% of the 12 cameras face")
  assert "--prepare=reconstruct" in warning
  # Too few cameras to tell an orbit: no warning.
  assert colmap.fold_warning(*_ring_poses(7, inward=False), "m") is None


def test_load_model_warns_on_a_folded_orbit(tmp_path, monkeypatch):
  write_scene(str(tmp_path), [f"{i}.png" for i in range(8)])
  said = []
  monkeypatch.setattr(colmap.logging, "warning", said.append)
  colmap.load_model(str(tmp_path))
  assert not said  # write_scene's ring looks inward
  monkeypatch.setattr(colmap, "_pose", lambda image: (
      np.diag([-1.0, 1.0, -1.0]) @ _pose(image.image_id, 8)[0],
      np.diag([-1.0, 1.0, -1.0]) @ _pose(image.image_id, 8)[1]))
  colmap.load_model(str(tmp_path))
  assert len(said) == 1 and "folded inside out" in said[0]


def _one_line_error(exc_info, *needles):
  msg = str(exc_info.value)
  assert "\n" not in msg, msg
  for needle in needles:
    assert str(needle) in msg, msg


@pytest.mark.parametrize("text", [False, True])
def test_reads_binary_and_text(tmp_path, text):
  names = ["b.png", "a.png", "c.png"]
  poses = write_scene(tmp_path, names, text=text, cams=(
      ("SIMPLE_PINHOLE", 64, 48, (55.0, 31.5, 24.25)),))
  model = colmap.load_model(str(tmp_path))
  assert model.names == ("a.png", "b.png", "c.png")   # sorted by name
  for i, name in enumerate(model.names):
    np.testing.assert_allclose(model.rotations[i], poses[name][0], atol=1e-9)
    np.testing.assert_allclose(model.translations[i], poses[name][1],
                               atol=1e-9)
  # SIMPLE_PINHOLE: fx = fy = f, principal point unchanged.
  np.testing.assert_allclose(model.intrinsics,
                             [[55.0, 55.0, 31.5, 24.25]] * 3, atol=1e-6)
  np.testing.assert_array_equal(model.sizes, [[64, 48]] * 3)
  assert not model.undistorted
  assert model.image_dir == os.path.join(str(tmp_path), "images")
  np.testing.assert_allclose(model.points[3], [0.3, -0.6, 0.5], atol=1e-6)
  np.testing.assert_array_equal(model.point_colors[3], [3, 6, 9])
  assert model.points.dtype == np.float32 and model.point_colors.dtype == (
      np.uint8)


def test_natural_name_order(tmp_path):
  # Numbered photos load in capture order, unpadded or not; on zero-padded
  # names (and names without numbers) it is the plain sorted order.
  write_scene(tmp_path, ["10.jpg", "9.jpg", "1.jpg", "2.jpg"])
  assert colmap.load_model(str(tmp_path)).names == (
      "1.jpg", "2.jpg", "9.jpg", "10.jpg")
  for scheme in ([f"{i:03d}.jpg" for i in (1, 2, 9, 10, 100, 184)],
                 ["DSCF5565.JPG", "DSCF5568.JPG", "DSCF5571.JPG"],
                 ["0clean000.png", "1extra001.png", "1extra010.png",
                  "2clutter000.png", "2clutter010.png"],
                 ["b.png", "a.png", "a-b.png", "a_1.png"]):
    assert sorted(scheme, key=colmap.natural_key) == sorted(scheme)
  assert sorted(["img10", "img2", "img02"], key=colmap.natural_key) == [
      "img02", "img2", "img10"]      # equal numbers: the string order


def test_distorted_camera_is_undistorted(tmp_path):
  write_scene(tmp_path / "s", ["a.png", "b.png"],
              cams=(("SIMPLE_RADIAL", 64, 48, (50.0, 32, 24, -0.2)),))
  cache = tmp_path / "cache"
  model = colmap.load_model(str(tmp_path / "s"), cache_dir=str(cache))
  assert model.undistorted
  assert model.image_dir.startswith(str(cache))
  undist = pycolmap.Reconstruction(model.sparse_dir)
  assert {c.model.name for c in undist.cameras.values()} == {"PINHOLE"}
  for name, (w, h) in zip(model.names, model.sizes):
    assert images.image_size(os.path.join(model.image_dir, name)) == (w, h)
  # Barrel distortion (k < 0) is undistorted to a different pinhole camera,
  # never read as the raw parameters.
  assert not np.allclose(model.intrinsics[0], [50, 50, 32, 24])
  # The scene itself is untouched, and a second load reuses the cache.
  assert sorted(os.listdir(tmp_path / "s")) == ["images", "sparse"]
  again = colmap.load_model(str(tmp_path / "s"), cache_dir=str(cache))
  assert again.image_dir == model.image_dir
  assert len([d for d in os.listdir(cache) if d.startswith("undist")]) == 1


def test_unreadable_image_is_not_cached(tmp_path):
  write_scene(tmp_path / "s", ["a.png", "b.png"],
              cams=(("SIMPLE_RADIAL", 64, 48, (50.0, 32, 24, -0.2)),))
  bad = tmp_path / "s" / "images" / "b.png"
  bad.write_bytes(b"not an image")
  cache = tmp_path / "cache"
  with pytest.raises(ValueError) as e:
    colmap.load_model(str(tmp_path / "s"), cache_dir=str(cache))
  _one_line_error(e, bad, "undistort")
  assert os.listdir(cache) == []          # no half-made cache entry


def test_zero_distortion_is_exact_pinhole(tmp_path):
  write_scene(tmp_path, ["a.png"], cams=(
      ("OPENCV", 64, 48, (50, 51, 32, 24, 0, 0, 0, 0)),))
  model = colmap.load_model(str(tmp_path), cache_dir=str(tmp_path / "c"))
  assert not model.undistorted and not (tmp_path / "c").exists()
  np.testing.assert_allclose(model.intrinsics[0], [50, 51, 32, 24])


def test_missing_model_folder(tmp_path):
  (tmp_path / "images").mkdir()
  with pytest.raises(FileNotFoundError) as e:
    colmap.load_model(str(tmp_path))
  _one_line_error(e, os.path.join("sparse", "0"), "COLMAP")


def test_missing_scene_folder(tmp_path):
  with pytest.raises(FileNotFoundError) as e:
    colmap.load_model(str(tmp_path / "nope"))
  _one_line_error(e, "nope")


@pytest.mark.parametrize("name", ["cameras", "images", "points3D"])
def test_empty_model_file(tmp_path, name):
  write_scene(tmp_path, ["a.png", "b.png"])
  path = tmp_path / "sparse" / "0" / f"{name}.bin"
  path.write_bytes(b"")
  with pytest.raises(ValueError) as e:
    colmap.load_model(str(tmp_path))
  _one_line_error(e, path, "re-export")


@pytest.mark.parametrize("name,keep", [("images", 100), ("points3D", 30),
                                       ("points3D", 9), ("rigs", 12),
                                       ("frames", 20), ("cameras", 30)])
def test_truncated_model_file(tmp_path, name, keep):
  # Truncated points3D.bin made pycolmap allocate without bound; the
  # structural check must refuse it before pycolmap reads it.
  write_scene(tmp_path, ["a.png", "b.png"])
  path = tmp_path / "sparse" / "0" / f"{name}.bin"
  path.write_bytes(path.read_bytes()[:keep])
  with pytest.raises(ValueError) as e:
    colmap.load_model(str(tmp_path))
  _one_line_error(e, path)


def test_trailing_garbage(tmp_path):
  write_scene(tmp_path, ["a.png"])
  path = tmp_path / "sparse" / "0" / "points3D.bin"
  path.write_bytes(path.read_bytes() + b"junk")
  with pytest.raises(ValueError) as e:
    colmap.load_model(str(tmp_path))
  _one_line_error(e, path, "trailing")


def test_missing_model_file(tmp_path):
  write_scene(tmp_path, ["a.png"])
  os.remove(tmp_path / "sparse" / "0" / "points3D.bin")
  with pytest.raises(FileNotFoundError) as e:
    colmap.load_model(str(tmp_path))
  _one_line_error(e, "points3D.bin")


def test_unknown_camera_model_binary(tmp_path):
  write_scene(tmp_path, ["a.png"])
  path = tmp_path / "sparse" / "0" / "cameras.bin"
  data = bytearray(path.read_bytes())
  data[12:16] = struct.pack("<i", 99)        # count u64, id i32, model i32
  path.write_bytes(bytes(data))
  with pytest.raises(ValueError) as e:
    colmap.load_model(str(tmp_path))
  _one_line_error(e, path, "unknown camera model id 99")


def test_unknown_camera_model_text(tmp_path):
  write_scene(tmp_path, ["a.png"], text=True)
  path = tmp_path / "sparse" / "0" / "cameras.txt"
  path.write_text(path.read_text().replace("PINHOLE", "MY_LENS"))
  with pytest.raises(ValueError) as e:
    colmap.load_model(str(tmp_path))
  _one_line_error(e, path, "MY_LENS")


def test_corrupt_text_model(tmp_path):
  write_scene(tmp_path, ["a.png"], text=True)
  path = tmp_path / "sparse" / "0" / "cameras.txt"
  path.write_text(path.read_text().replace(" 64 48 ", " sixty 48 "))
  with pytest.raises(ValueError) as e:
    colmap.load_model(str(tmp_path))
  _one_line_error(e, os.path.join(str(tmp_path), "sparse", "0"), "corrupt")


def test_empty_text_model(tmp_path):
  sparse = tmp_path / "sparse" / "0"
  sparse.mkdir(parents=True)
  for name in ("cameras", "images", "points3D"):
    (sparse / f"{name}.txt").write_text("")
  with pytest.raises(ValueError) as e:
    colmap.load_model(str(tmp_path))
  _one_line_error(e, sparse, "no registered images")


def test_missing_image(tmp_path):
  write_scene(tmp_path, ["a.png", "b.png"])
  os.remove(tmp_path / "images" / "b.png")
  with pytest.raises(FileNotFoundError) as e:
    colmap.load_model(str(tmp_path))
  _one_line_error(e, tmp_path / "images" / "b.png")


def test_non_perspective_camera_refused(tmp_path):
  write_scene(tmp_path, ["a.png"], cams=(
      ("EQUIRECTANGULAR", 64, 32, (32, 16)),))
  with pytest.raises(ValueError) as e:
    colmap.load_model(str(tmp_path), cache_dir=str(tmp_path / "c"))
  _one_line_error(e, "EQUIRECTANGULAR", "perspective")


def test_default_cache_dir(monkeypatch, tmp_path):
  monkeypatch.setenv("CLIPGS_JAX_CACHE", str(tmp_path / "root"))
  a = colmap.default_cache_dir("/data/scene")
  assert a.startswith(str(tmp_path / "root")) and "scene-" in a
  assert a != colmap.default_cache_dir("/other/scene")
  monkeypatch.delenv("CLIPGS_JAX_CACHE")
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
  assert colmap.cache_root() == str(tmp_path / "xdg" / "clipgs_jax")


@needs_data
def test_bird_model():
  model = colmap.load_model(str(DATA / "bird"))
  assert len(model.names) == 184 and list(model.names) == sorted(model.names)
  assert not model.undistorted
  np.testing.assert_array_equal(model.sizes, [[544, 960]] * 184)
  # SIMPLE_PINHOLE: one focal length per image.
  np.testing.assert_array_equal(model.intrinsics[:, 0], model.intrinsics[:, 1])
  rot = model.rotations
  np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1),
                             np.broadcast_to(np.eye(3), rot.shape), atol=1e-9)
  assert model.points.shape[0] > 1000


@needs_data
def test_real_model_copy_with_empty_images(tmp_path):
  shutil.copytree(DATA / "bird" / "sparse", tmp_path / "sparse")
  (tmp_path / "images").mkdir()
  with pytest.raises(FileNotFoundError) as e:
    colmap.load_model(str(tmp_path))
  # The empty folder is named, with the model's first image as an example
  # (a single missing image is a row of tests/test_bad_inputs.py).
  _one_line_error(e, tmp_path / "images", "is empty", "001.jpg")
