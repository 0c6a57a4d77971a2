"""Pinhole cameras in the COLMAP/OpenCV convention.

Conventions, stated once for the whole package:
  * World-to-camera: x_cam = R @ x_world + t, with R a rotation [3, 3].
  * Camera axes: +x right, +y down, +z forward (into the scene).
  * Pixels: (u, v) = (fx * x / z + cx, fy * y / z + cy), in pixels, with the
    centre of pixel (row i, column j) at (j + 0.5, i + 0.5). COLMAP uses the
    same convention, so its intrinsics are used unchanged; so do the
    transforms.json files of instant-ngp and nerfstudio (fl_x, cx, ...).
  * Images are row-major [height, width, channels].
  * transforms.json (NeRF-synthetic, instant-ngp, nerfstudio) stores
    camera-to-world matrices in the OpenGL/Blender axes (+x right, +y up,
    +z backward: the camera looks down -z); `from_opengl_camera_to_world`
    is the one conversion.
"""

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

# OpenGL camera axes in ours: x stays, y (up) and z (backward) flip.
_OPENGL_AXES = np.diag([1.0, -1.0, -1.0])
# Largest |R R^T - I| entry accepted as a rotation (float32 poses written
# with 6-7 digits are orthonormal to ~1e-6; a scale or shear is far above).
ROTATION_TOLERANCE = 1e-3


@flax.struct.dataclass
class Camera:
  """One pinhole camera.

  Attributes:
    rotation: float [3, 3], world-to-camera rotation R.
    translation: float [3], world-to-camera translation t.
    fx, fy: float [], focal lengths in pixels.
    cx, cy: float [], principal point in pixels (pixel centres at +0.5).
    width, height: image size in pixels; static, since they fix array shapes.
  """
  rotation: Any
  translation: Any
  fx: Any
  fy: Any
  cx: Any
  cy: Any
  width: int = flax.struct.field(pytree_node=False)
  height: int = flax.struct.field(pytree_node=False)

  @classmethod
  def create(cls, rotation, translation, fx, fy, cx, cy, width, height,
             dtype=np.float32) -> "Camera":
    """Builds a camera from host values, validating them (see `validate`)."""
    cam = cls(
        rotation=np.asarray(rotation, dtype),
        translation=np.asarray(translation, dtype),
        fx=np.asarray(fx, dtype), fy=np.asarray(fy, dtype),
        cx=np.asarray(cx, dtype), cy=np.asarray(cy, dtype),
        width=int(width), height=int(height))
    validate(cam)
    return cam


def _is_traced(x) -> bool:
  return isinstance(x, jax.core.Tracer)


def validate(cam: Camera, name: str = "camera") -> None:
  """Raises ValueError for a camera no renderer can use.

  Shapes and image size are always checked; values (finite pose, positive
  focal lengths) are checked when they are concrete, i.e. outside jit.
  """
  if not isinstance(cam, Camera):
    raise ValueError(f"{name} must be a clipgs_jax.camera.Camera, got "
                     f"{type(cam).__name__}.")
  if (not isinstance(cam.width, (int, np.integer)) or
      not isinstance(cam.height, (int, np.integer)) or
      cam.width <= 0 or cam.height <= 0):
    raise ValueError(f"{name}: image size must be positive integers, got "
                     f"width={cam.width!r}, height={cam.height!r}.")
  shapes = {"rotation": (3, 3), "translation": (3,), "fx": (), "fy": (),
            "cx": (), "cy": ()}
  for field, shape in shapes.items():
    value = getattr(cam, field)
    if np.shape(value) != shape:
      raise ValueError(f"{name}.{field} must have shape {shape}, got "
                       f"{np.shape(value)}.")
    if not np.issubdtype(np.asarray(value).dtype if not _is_traced(value)
                         else value.dtype, np.floating):
      raise ValueError(f"{name}.{field} must be a float array.")
  if any(_is_traced(getattr(cam, f)) for f in shapes):
    return
  for field in shapes:
    if not np.all(np.isfinite(np.asarray(getattr(cam, field)))):
      raise ValueError(f"{name}.{field} has non-finite values: "
                       f"{np.asarray(getattr(cam, field))}.")
  for field in ("fx", "fy"):
    if float(np.asarray(getattr(cam, field))) <= 0:
      raise ValueError(f"{name}.{field} must be positive, got "
                       f"{float(np.asarray(getattr(cam, field)))}.")
  rot = np.asarray(cam.rotation, np.float64)
  if np.abs(rot @ rot.T - np.eye(3)).max() > ROTATION_TOLERANCE:
    raise ValueError(f"{name}.rotation is not a rotation matrix "
                     "(R @ R.T != I); pass a world-to-camera rotation.")


def from_opengl_camera_to_world(matrix) -> tuple[np.ndarray, np.ndarray]:
  """World-to-camera (R [3, 3], t [3]), float64, of an OpenGL camera.

  Args:
    matrix: float [4, 4] (or [3, 4]), a rigid camera-to-world transform in
      the OpenGL axes (transforms.json's `transform_matrix`); the caller
      checks that it is rigid.
  """
  m = np.asarray(matrix, np.float64)
  # Columns of the camera-to-world rotation are the camera axes in the
  # world; flipping y and z gives ours, and R is its transpose.
  rotation = (m[:3, :3] @ _OPENGL_AXES).T
  return rotation, -rotation @ m[:3, 3]


def camera_at(cameras: Camera, i) -> Camera:
  """The i-th camera of stacked cameras.

  Args:
    cameras: Camera with a leading [V] axis on its array fields.
    i: int, or an int32 [] array that may be traced under jit.

  Returns:
    Camera with unbatched fields (numpy for a Python int and numpy
    fields, jax arrays otherwise).
  """
  if isinstance(i, (int, np.integer)) and isinstance(cameras.fx, np.ndarray):
    return jax.tree.map(lambda x: x[i], cameras)
  return jax.tree.map(lambda x: jnp.take(jnp.asarray(x), i, axis=0), cameras)


def camera_center(cam: Camera, xnp=np):
  """float [..., 3], the camera centre(s) in world coordinates, -R^T t.

  Works on one camera and on cameras stacked along leading axes.
  """
  return -xnp.einsum("...ji,...j->...i", xnp.asarray(cam.rotation),
                     xnp.asarray(cam.translation))


def tan_half_fov(cam: Camera, xnp=np):
  """(tan(fov_x / 2), tan(fov_y / 2)) from the focal lengths."""
  return (0.5 * cam.width / xnp.asarray(cam.fx),
          0.5 * cam.height / xnp.asarray(cam.fy))


def look_at(eye, target, up, fx, fy, width, height, dtype=np.float32
            ) -> Camera:
  """A camera at `eye` looking at `target`; `up` is the world up direction.

  Since +y points down in the image, the camera's y axis is -up projected
  onto the image plane.
  """
  eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
  z = target - eye
  z /= np.linalg.norm(z)
  x = np.cross(z, up)       # right-handed with y = -up: x = y cross z
  if np.linalg.norm(x) < 1e-9:
    raise ValueError("look_at: `up` is parallel to the viewing direction.")
  x /= np.linalg.norm(x)
  y = np.cross(z, x)        # points down in the image, i.e. along -up
  rotation = np.stack([x, y, z])   # rows are the camera axes in world frame
  translation = -rotation @ eye
  return Camera.create(rotation, translation, fx, fy, width / 2, height / 2,
                       width, height, dtype=dtype)
