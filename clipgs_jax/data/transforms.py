"""transforms.json scenes (NeRF-synthetic, instant-ngp, nerfstudio) as a
colmap.Model: poses, pinhole intrinsics, the capture's own test split.

A scene folder holds `transforms_train.json` (and `transforms_test.json`,
the held-out views; `transforms_val.json` is not read), or one
`transforms.json`. Each file has `frames`, a list of {file_path,
transform_matrix}, and intrinsics given once for the file or per frame:
`camera_angle_x` (and `camera_angle_y`) or `fl_x`/`fl_y`, `cx`/`cy`, `w`/`h`
(defaults: square pixels, the principal point at the image centre, the size
of the image file). Poses are OpenGL camera-to-world matrices, converted by
camera.from_opengl_camera_to_world. Points come from nerfstudio's
`ply_file_path` when given, else none (initialize.py then draws random
points in the cameras' box, as 3DGS does for the synthetic scenes).
"""

import json
import math
import os

import numpy as np

from clipgs_jax import camera
from clipgs_jax.data import colmap
from clipgs_jax.data import images

WHOLE = "transforms.json"
TRAIN = "transforms_train.json"
TEST = "transforms_test.json"
# NeRF-synthetic names its frames without an extension ("./train/r_0");
# the first of these that exists is the photo.
EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".exr")
# Distortion terms, by instant-ngp's and nerfstudio's names: a pinhole
# camera has them all zero (a distorted camera is never taken as one).
_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
# nerfstudio's camera_model values that are pinhole with zero distortion.
_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
_FRAME_FIX = ("write each frame as {\"file_path\": ..., \"transform_matrix\": "
              "[[4 numbers] x 4]}")


def files(path: str) -> tuple[str, str | None] | None:
  """(the training frames' file, the test frames' file or None) of a
  transforms scene folder, or None when `path` has no transforms file.

  transforms_train.json wins over transforms.json when both are present.
  """
  train = os.path.join(path, TRAIN)
  if os.path.isfile(train):
    test = os.path.join(path, TEST)
    return train, test if os.path.isfile(test) else None
  whole = os.path.join(path, WHOLE)
  return (whole, None) if os.path.isfile(whole) else None


def _read(path: str) -> dict:
  """The checked top level of one transforms file."""
  try:
    with open(path) as f:
      data = json.load(f)
  except json.JSONDecodeError as e:
    raise ValueError(f"{path} is not valid JSON ({e.msg} at line {e.lineno} "
                     f"column {e.colno}); fix the file.") from None
  except UnicodeDecodeError:
    raise ValueError(f"{path} is not a text file; write it as UTF-8 "
                     "JSON.") from None
  if not isinstance(data, dict):
    raise ValueError(f"{path} holds a JSON {type(data).__name__}, not an "
                     "object with 'frames'; " + _FRAME_FIX + ".")
  frames = data.get("frames")
  if not isinstance(frames, list) or not frames:
    raise ValueError(f"{path} has no frames ('frames' must be a non-empty "
                     "list, one entry per photo); " + _FRAME_FIX + ".")
  return data


def _number(value, where: str, key: str) -> float:
  if isinstance(value, bool) or not isinstance(value, (int, float)) or (
      not math.isfinite(value)):
    raise ValueError(f"{where}: {key}={value!r} is not a finite number; "
                     "write it as a JSON number.")
  return float(value)


def _field(frame: dict, top: dict, key: str, where: str) -> float | None:
  """A number given by the frame, else by the file; None if neither."""
  value = frame.get(key, top.get(key))
  return None if value is None else _number(value, where, key)


def _image_path(folder: str, frame: dict, where: str) -> str:
  """The photo a frame names, with an extension tried when it has none."""
  name = frame.get("file_path")
  if not isinstance(name, str) or not name:
    raise ValueError(f"{where}: no file_path (a photo path relative to "
                     f"{folder}); " + _FRAME_FIX + ".")
  path = os.path.normpath(os.path.join(folder, name))
  for candidate in (path,) + tuple(path + e for e in EXTENSIONS):
    if os.path.isfile(candidate):
      return candidate
  tried = "" if os.path.splitext(name)[1] else (
      f" (also with {', '.join(EXTENSIONS[:3])}, ...)")
  raise FileNotFoundError(f"{where}: photo {path}{tried} does not exist; fix "
                          "file_path or add the photo.")


def _pose(frame: dict, where: str) -> tuple[np.ndarray, np.ndarray]:
  """World-to-camera (R, t) of a frame's rigid OpenGL camera-to-world."""
  matrix = frame.get("transform_matrix")
  try:
    m = np.array(matrix, np.float64)
  except (TypeError, ValueError):
    m = np.zeros(0)
  if m.shape not in ((4, 4), (3, 4)):
    raise ValueError(f"{where}: transform_matrix must be 4 rows of 4 numbers "
                     f"(camera-to-world), got {str(matrix)[:60]}; "
                     + _FRAME_FIX + ".")
  if not np.all(np.isfinite(m)):
    raise ValueError(f"{where}: transform_matrix has non-finite values; "
                     "write finite numbers.")
  rot = m[:3, :3]
  if (m.shape == (4, 4) and np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-6) or (
      np.abs(rot @ rot.T - np.eye(3)).max() > camera.ROTATION_TOLERANCE) or (
          np.linalg.det(rot) < 0):
    raise ValueError(f"{where}: transform_matrix is not rigid (its 3x3 part "
                     "must be a rotation: no scale, shear or mirror; last row "
                     "0 0 0 1); write the camera-to-world pose with any "
                     "scene scale in the translation.")
  return camera.from_opengl_camera_to_world(m)


def _intrinsics(frame: dict, top: dict, path: str, where: str
                ) -> tuple[np.ndarray, tuple[int, int]]:
  """((fx, fy, cx, cy), (width, height)) of a frame: its own values, else
  the file's, else from the photo (size) and square pixels."""
  model = frame.get("camera_model", top.get("camera_model", "PINHOLE"))
  if model not in _PINHOLE_MODELS:
    raise ValueError(f"{where}: camera_model {model!r} is not a pinhole "
                     "camera; undistort the photos to PINHOLE first.")
  for key in _DISTORTION:
    if _field(frame, top, key, where):
      raise ValueError(f"{where}: distortion {key} is not 0; undistort the "
                       "photos (e.g. COLMAP's image_undistorter) and write "
                       "pinhole intrinsics.")
  w, h = _field(frame, top, "w", where), _field(frame, top, "h", where)
  if w is None or h is None:
    width, height = images.image_size(path)
  else:
    width, height = int(w), int(h)
    if width != w or height != h or width < 1 or height < 1:
      raise ValueError(f"{where}: w={w:g}, h={h:g} must be positive whole "
                       "pixel counts; fix them or leave them out.")
  fx = _focal(frame, top, where, "x", width)
  fy = _focal(frame, top, where, "y", height)
  if fx is None:
    raise ValueError(f"{where}: no focal length; give camera_angle_x "
                     "(radians) or fl_x (pixels) in the file or the frame.")
  cx, cy = _field(frame, top, "cx", where), _field(frame, top, "cy", where)
  intrinsics = np.array([fx, fx if fy is None else fy,
                         width / 2 if cx is None else cx,
                         height / 2 if cy is None else cy])
  return intrinsics, (width, height)


def _focal(frame: dict, top: dict, where: str, axis: str, size: int
           ) -> float | None:
  """fl_{axis} in pixels, or from camera_angle_{axis}; None if neither."""
  focal = _field(frame, top, f"fl_{axis}", where)
  angle = _field(frame, top, f"camera_angle_{axis}", where)
  if focal is None and angle is not None:
    if not 0 < angle < math.pi:
      raise ValueError(f"{where}: camera_angle_{axis}={angle:g} is not a "
                       "field of view in (0, pi) radians; fix it.")
    focal = 0.5 * size / math.tan(0.5 * angle)
  if focal is not None and focal <= 0:
    raise ValueError(f"{where}: fl_{axis}={focal:g} must be positive; fix "
                     "it.")
  return focal


def _points(folder: str, top: dict, where: str
            ) -> tuple[np.ndarray, np.ndarray]:
  """nerfstudio's point cloud (ply_file_path), or none."""
  name = top.get("ply_file_path")
  if name is None:
    return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
  import plyfile  # pylint: disable=import-outside-toplevel
  path = os.path.normpath(os.path.join(folder, str(name)))
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{where}: ply_file_path {path} does not exist; "
                            "fix it or leave it out (random points).")
  try:
    vertex = plyfile.PlyData.read(path)["vertex"]
    xyz = np.stack([vertex[k] for k in "xyz"], -1).astype(np.float32)
    names = vertex.data.dtype.names
    rgb = (np.stack([vertex[k] for k in ("red", "green", "blue")], -1)
           if "red" in names else np.full_like(xyz, 128))
  except (KeyError, ValueError, plyfile.PlyParseError) as e:
    raise ValueError(f"{path} (ply_file_path) is not a point cloud with "
                     f"x, y, z vertices ({e}); write it again.") from None
  return xyz.reshape(-1, 3), rgb.astype(np.uint8).reshape(-1, 3)


def load_model(path: str) -> colmap.Model:
  """The transforms scene in folder `path` as a colmap.Model.

  Its names are the photos' paths relative to `path`, in natural order;
  `test_views` are those of transforms_test.json, or None when the scene
  has no test file (then every 8th view is held out, as for COLMAP).

  Raises:
    ValueError: a malformed file or frame; the message names the file,
      the frame and the field, and says the fix.
    FileNotFoundError: no transforms file, or a frame's photo is missing.
  """
  found = files(path)
  if found is None:
    raise FileNotFoundError(f"no {WHOLE} or {TRAIN} in {path}; pass a "
                            "transforms scene folder.")
  frames, top_points = [], None
  for file, is_test in zip(found, (False, True)):
    if file is None:
      continue
    top = _read(file)
    for i, frame in enumerate(top["frames"]):
      where = f"{file}: frames[{i}]"
      if not isinstance(frame, dict):
        raise ValueError(f"{where} is not an object; " + _FRAME_FIX + ".")
      image = _image_path(path, frame, where)
      rotation, translation = _pose(frame, where)
      intrinsics, size = _intrinsics(frame, top, image, where)
      frames.append((os.path.relpath(image, path), rotation, translation,
                     intrinsics, size, is_test, where))
    if top_points is None:
      top_points = _points(path, top, file)
  frames.sort(key=lambda f: colmap.natural_key(f[0]))
  names = [f[0] for f in frames]
  for (name, *_, where), prev in zip(frames[1:], names):
    if name == prev:
      raise ValueError(f"{where}: photo {name} is named by another frame "
                       "too; give each photo one frame.")
  points, colors = top_points
  return colmap.Model(
      names=tuple(names),
      rotations=np.stack([f[1] for f in frames]),
      translations=np.stack([f[2] for f in frames]),
      intrinsics=np.stack([f[3] for f in frames]),
      sizes=np.array([f[4] for f in frames], np.int64),
      points=points, point_colors=colors, image_dir=path,
      sparse_dir=found[0], undistorted=False,
      test_views=(tuple(i for i, f in enumerate(frames) if f[5])
                  if found[1] is not None else None))
