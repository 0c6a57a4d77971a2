"""transforms.json scenes (data/transforms.py): cameras, photos with alpha,
splits, malformed files, and the real lego and bird captures."""

import json
import os
import shutil

import numpy as np
import plyfile
import pytest

from clipgs_jax import camera
from clipgs_jax import config
from clipgs_jax import train
from clipgs_jax.data import colmap
from clipgs_jax.data import images
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.data import transforms
from test_bad_inputs import _InProcess  # pylint: disable=g-bad-import-order
import shared_data  # tests/, on sys.path under pytest

SIZE = (32, 24)
# OpenGL camera axes in OpenCV's: y and z flip. Written here independently
# of camera.py, so that the test checks the library's conversion.
_FLIP = np.diag([1.0, -1.0, -1.0])


def ring(n: int, radius: float = 3.0) -> list[camera.Camera]:
  """n cameras on a ring around the origin, looking at it."""
  return [camera.look_at(
      [radius * np.cos(a), radius * np.sin(a), 1.0], [0, 0, 0], [0, 0, 1],
      20.0, 20.0, *SIZE) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]


def _opengl_matrix(cam: camera.Camera) -> list[list[float]]:
  """The 4x4 OpenGL camera-to-world matrix of an OpenCV world-to-camera."""
  rot = np.asarray(cam.rotation, np.float64).T @ _FLIP
  centre = camera.camera_center(cam).astype(np.float64)
  return np.vstack([np.hstack([rot, centre[:, None]]), [0, 0, 0, 1]]).tolist()


def write_transforms(root, n=9, *, name="transforms.json", first=0,
                     alpha=True, top=None, frame_extra=None,
                     extension=False):
  """A transforms scene of n RGBA (or RGB) photos under root/frames/.

  Photo i is red where its alpha is 1 (left half), transparent elsewhere.
  Returns the cameras.
  """
  cams = ring(n + first)[first:]
  os.makedirs(os.path.join(root, "frames"), exist_ok=True)
  frames = []
  for i, cam in enumerate(cams, first):
    pixels = np.zeros(SIZE[::-1] + (4 if alpha else 3,))
    pixels[:, : SIZE[0] // 2, 0] = 1.0
    if alpha:
      pixels[:, : SIZE[0] // 2, 3] = 1.0
    images.write_png(os.path.join(root, "frames", f"f{i}.png"), pixels)
    frames.append({"file_path": f"./frames/f{i}" + (".png" if extension
                                                     else ""),
                   "transform_matrix": _opengl_matrix(cam),
                   **((frame_extra or {}).get(i, {}))})
  data = {"camera_angle_x": 2 * np.arctan(0.5 * SIZE[0] / 20.0)}
  data.update(top or {})
  data["frames"] = frames
  with open(os.path.join(root, name), "w") as f:
    json.dump(data, f)
  return cams


def _load(root, **kwargs):
  return scene_lib.load_scene(str(root), cache_dir=str(root / "cache"),
                              **kwargs)


def test_cameras_photos_and_split(tmp_path):
  cams = write_transforms(tmp_path)
  scene = _load(tmp_path)
  # Every 8th frame in natural order (f0, f1, ..., f8) is a test view.
  assert scene.test.names == ("frames/f0.png", "frames/f8.png")
  assert len(scene.train) == 7
  got = scene.train.cameras
  for k, i in enumerate(range(1, 8)):
    np.testing.assert_allclose(got.rotation[k], cams[i].rotation, atol=1e-6)
    np.testing.assert_allclose(got.translation[k], cams[i].translation,
                               atol=1e-5)
  # camera_angle_x alone: square pixels, the principal point in the middle.
  np.testing.assert_allclose(got.fx, 20.0, rtol=1e-6)
  np.testing.assert_allclose(got.fy, 20.0, rtol=1e-6)
  np.testing.assert_allclose(got.cx, 16.0)
  np.testing.assert_allclose(got.cy, 12.0)
  assert len(scene.points) == 0           # random points at initialization
  # RGBA composited onto white: red where opaque, white where transparent.
  assert scene.background == (1.0, 1.0, 1.0)
  np.testing.assert_array_equal(scene.train.images[0, 0, 0], [1, 0, 0])
  np.testing.assert_array_equal(scene.train.images[0, 0, -1], [1, 1, 1])


def test_black_background_test_file_and_intrinsics(tmp_path):
  top = {"fl_x": 21.0, "fl_y": 22.0, "cx": 15.5, "cy": 12.5, "w": 32, "h": 24}
  write_transforms(tmp_path, 3, name=transforms.TRAIN, top=top,
                   frame_extra={1: {"fl_x": 30.0}}, extension=True)
  write_transforms(tmp_path, 2, name=transforms.TEST, first=3, top=top)
  scene = _load(tmp_path, background="black", downscale=2)
  assert scene.test.names == ("frames/f3.png", "frames/f4.png")
  assert scene.train.names == ("frames/f0.png", "frames/f1.png",
                               "frames/f2.png")
  # Per-frame values win; downscale 2 halves the intrinsics.
  np.testing.assert_allclose(scene.train.cameras.fx, [10.5, 15.0, 10.5])
  np.testing.assert_allclose(scene.train.cameras.fy, 11.0)
  np.testing.assert_allclose(scene.train.cameras.cx, 7.75)
  assert scene.background == (0.0, 0.0, 0.0)
  np.testing.assert_array_equal(scene.train.images[0, 0, -1], [0, 0, 0])


def test_rgb_photos_keep_the_render_background(tmp_path):
  write_transforms(tmp_path, alpha=False)
  assert _load(tmp_path).background is None


def test_pack_keeps_the_background(tmp_path):
  write_transforms(tmp_path)
  out = str(tmp_path / "lego.npz")
  scene_lib.pack(str(tmp_path), out, 1, cache_dir=str(tmp_path / "cache"))
  packed = scene_lib.load_scene(out)
  assert packed.background == (1.0, 1.0, 1.0)
  np.testing.assert_array_equal(packed.train.images,
                                _load(tmp_path).train.images)
  with pytest.raises(ValueError, match="--config.data.background=white"):
    scene_lib.load_scene(out, background="black")


_RIGID = _opengl_matrix(ring(1)[0])
_SCALED = (np.array(_RIGID) * [[2], [2], [2], [1]]).tolist()


class BadTransformsTest(_InProcess):
  """A malformed transforms scene: one line naming the field and the fix,
  no output left behind."""

  def write(self, **kwargs):
    write_transforms(self.scene, **kwargs)

  def rewrite(self, edit):
    path = os.path.join(self.scene, "transforms.json")
    with open(path) as f:
      data = json.load(f)
    edit(data)
    with open(path, "w") as f:
      json.dump(data, f)

  def test_no_frames(self):
    self.write()
    self.rewrite(lambda d: d.update(frames=[]))
    self.assert_one_line(self.load, says=("transforms.json", "no frames",
                                          "file_path"))

  def test_not_json(self):
    self.write()
    with open(os.path.join(self.scene, "transforms.json"), "a") as f:
      f.write("}")
    self.assert_one_line(self.load, says=("not valid JSON", "line 1",
                                          "fix the file"))

  def test_missing_photo(self):
    self.write()
    os.remove(os.path.join(self.scene, "frames", "f3.png"))
    self.assert_one_line(self.load, says=("frames[3]", "f3", "does not exist",
                                          "fix file_path"))

  def test_non_rigid_matrix(self):
    self.write(frame_extra={2: {"transform_matrix": _SCALED}})
    self.assert_one_line(self.load, says=("frames[2]", "transform_matrix",
                                          "not rigid", "no scale"))

  def test_matrix_of_wrong_shape(self):
    self.write(frame_extra={1: {"transform_matrix": [[1, 0], [0, 1]]}})
    self.assert_one_line(self.load, says=("frames[1]", "4 rows of 4"))

  def test_no_focal_length(self):
    self.write()
    self.rewrite(lambda d: d.pop("camera_angle_x"))
    self.assert_one_line(self.load, says=("frames[0]", "no focal length",
                                          "camera_angle_x", "fl_x"))

  def test_distorted_camera(self):
    self.write(top={"k1": 0.1})
    self.assert_one_line(self.load, says=("k1", "undistort"))

  def test_fisheye_camera(self):
    self.write(top={"camera_model": "OPENCV_FISHEYE"})
    self.assert_one_line(self.load, says=("OPENCV_FISHEYE", "undistort"))

  def test_field_of_another_type(self):
    self.write(frame_extra={4: {"fl_x": "wide"}})
    self.assert_one_line(self.load, says=("frames[4]", "fl_x='wide'",
                                          "JSON number"))

  def test_one_photo_in_two_frames(self):
    self.write(frame_extra={5: {"file_path": "frames/f4.png"}})
    self.assert_one_line(self.load, says=("f4.png", "another frame"))


@shared_data.needs_data("lego")
def test_lego():
  scene = scene_lib.load_scene(str(shared_data.DATA / "lego"), downscale=8)
  assert (len(scene.train), len(scene.test)) == (87, 13)
  assert scene.test.names[:2] == ("train/r_0.png", "train/r_8.png")
  assert scene.train.images.shape == (87, 50, 50, 3)
  # White behind the model: every corner of every photo.
  assert scene.train.images[:, [0, 0, -1, -1], [0, -1, 0, -1]].min() > 0.99
  with open(shared_data.DATA / "lego" / transforms.TRAIN) as f:
    angle = json.load(f)["camera_angle_x"]
  np.testing.assert_allclose(scene.train.cameras.fx,
                             25.0 / np.tan(angle / 2), rtol=1e-6)


def _as_transforms(model: colmap.Model, root) -> None:
  """Writes a COLMAP model as a nerfstudio-style transforms scene at root:
  per-frame intrinsics, the photos linked, the points as a PLY."""
  os.symlink(model.image_dir, os.path.join(root, "images"))
  frames = []
  for name, rot, t, (fx, fy, cx, cy), (w, h) in zip(
      model.names, model.rotations, model.translations, model.intrinsics,
      model.sizes):
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rot.T @ _FLIP, -rot.T @ t
    frames.append({"file_path": f"images/{name}", "fl_x": fx, "fl_y": fy,
                   "cx": cx, "cy": cy, "w": int(w), "h": int(h),
                   "transform_matrix": c2w.tolist()})
  vertex = np.empty(len(model.points), [(k, "f4") for k in "xyz"] +
                    [(k, "u1") for k in ("red", "green", "blue")])
  for k, column in zip("xyz", model.points.T):
    vertex[k] = column
  for k, column in zip(("red", "green", "blue"), model.point_colors.T):
    vertex[k] = column
  plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(
      os.path.join(root, "points.ply"))
  with open(os.path.join(root, "transforms.json"), "w") as f:
    json.dump({"camera_model": "PINHOLE", "ply_file_path": "points.ply",
               "frames": frames[::-1]}, f)      # any order: names sort


@shared_data.needs_data("bird")
def test_bird_round_trip(tmp_path):
  bird = str(shared_data.DATA / "bird")
  root = tmp_path / "bird_transforms"
  root.mkdir()
  _as_transforms(colmap.load_model(bird), str(root))
  a = scene_lib.load_scene(bird, downscale=32)
  b = scene_lib.load_scene(str(root), downscale=32)
  assert a.test.names == tuple(n.removeprefix("images/")
                               for n in b.test.names)
  for split in ("train", "test"):
    va, vb = getattr(a, split), getattr(b, split)
    for field in ("rotation", "translation", "fx", "fy", "cx", "cy"):
      np.testing.assert_allclose(getattr(vb.cameras, field),
                                 getattr(va.cameras, field), atol=2e-6,
                                 rtol=1e-6, err_msg=f"{split} {field}")
    np.testing.assert_array_equal(vb.images, va.images)
  np.testing.assert_array_equal(b.points, a.points)
  np.testing.assert_array_equal(b.point_colors, a.point_colors)
  assert b.background is None and b.extent == pytest.approx(a.extent)
  cfg = config.Config(
      gaussians=config.GaussiansConfig(sh_degree=0, min_capacity=256),
      train=config.TrainConfig(steps=5, log_every=5, eval_every=5,
                               checkpoint_every=0))
  psnr = [train.fit(train.resolve(cfg, s), s, str(tmp_path / name),
                    progress=False).curve[-1]["test_psnr"]
          for s, name in ((a, "a"), (b, "b"))]
  assert psnr[1] == pytest.approx(psnr[0], abs=1e-3), psnr
  shutil.rmtree(root)
