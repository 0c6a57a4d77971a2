"""EWA projection of 3D Gaussians to screen-space splats."""

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

from clipgs_jax import camera as camera_lib
from clipgs_jax import gaussians
from clipgs_jax import numerics
from clipgs_jax import sh

# Added to the 2D covariance diagonal (pixels^2): a low-pass filter so every
# splat covers about one pixel, as in the reference 3DGS rasterizer.
LOW_PASS = 0.3
# View-space x/z and y/z are clamped to this multiple of tan(fov/2) before
# the projection Jacobian, so Gaussians far outside the view do not get
# exploding Jacobians (reference 3DGS value).
FRUSTUM_CLAMP = 1.3
# Splats whose projected standard deviation exceeds this (pixels) are culled:
# their covariance determinant ~ std^4 would overflow float32 (3.4e38).
MAX_PROJECTED_STD = 1e8
# Alpha below this is not blended (8-bit colour cannot show it).
ALPHA_THRESHOLD = 1.0 / 255.0
# Relative and absolute slack on the binning extent, so float rounding at the
# ellipse edge never drops a tile where the blend would find alpha >= 1/255.
_EXTENT_SLACK = (1e-3, 1e-2)

_HI = jax.lax.Precision.HIGHEST


@flax.struct.dataclass
class Projected:
  """Per-Gaussian screen-space quantities.

  Attributes:
    means2d: float [N, 2], centre in pixels (x right, y down).
    conics: float [N, 3], (a, b, c) of the inverse 2D covariance
      [[a, b], [b, c]].
    depths: float [N], view-space z.
    colors: float [N, 3], RGB from SH for this view.
    opacities: float [N], in [0, 1].
    extents: float [N, 2], half-width and half-height (pixels) of the box
      outside which alpha < 1/255; zero for culled Gaussians.
    valid: bool [N], alive, in front of the near plane, positive-definite
      covariance and opacity >= 1/255.
  """
  means2d: Any
  conics: Any
  depths: Any
  colors: Any
  opacities: Any
  extents: Any
  valid: Any


def project(params: gaussians.GaussianParams, alive: jax.Array,
            cam: camera_lib.Camera, *, near: float,
            sh_degree: jax.Array | int) -> Projected:
  """Projects all C slots; culled ones get valid = False and safe values."""
  act = gaussians.activate(params)
  dtype = act.means.dtype
  rot = jnp.asarray(cam.rotation, dtype)
  p_cam = jnp.matmul(act.means, rot.T, precision=_HI) + jnp.asarray(
      cam.translation, dtype)                                    # [N, 3]
  z = p_cam[:, 2]
  in_front = alive & (z > near)
  # Sanitise the dead branch's input: culled slots divide by 1, not by 0.
  z_s = jnp.where(in_front, z, 1.0)
  x_s = jnp.where(in_front, p_cam[:, 0], 0.0)
  y_s = jnp.where(in_front, p_cam[:, 1], 0.0)
  fx, fy = jnp.asarray(cam.fx, dtype), jnp.asarray(cam.fy, dtype)
  cx, cy = jnp.asarray(cam.cx, dtype), jnp.asarray(cam.cy, dtype)
  tan_x, tan_y = camera_lib.tan_half_fov(cam, jnp)
  lim_x, lim_y = FRUSTUM_CLAMP * tan_x, FRUSTUM_CLAMP * tan_y
  tx = jnp.clip(x_s / z_s, -lim_x, lim_x) * z_s
  ty = jnp.clip(y_s / z_s, -lim_y, lim_y) * z_s
  zero = jnp.zeros_like(z_s)
  jac = jnp.stack([
      jnp.stack([fx / z_s, zero, -fx * tx / (z_s * z_s)], -1),
      jnp.stack([zero, fy / z_s, -fy * ty / (z_s * z_s)], -1)], -2)  # [N,2,3]
  # M = J W R_g S, so that the 2D covariance is M M^T.
  m = jnp.einsum("nij,jk,nkl->nil", jac, rot, act.rotations, precision=_HI)
  m = m * act.scales[:, None, :]                                 # [N, 2, 3]
  ok = in_front & jnp.all(jnp.abs(m) < MAX_PROJECTED_STD, axis=(1, 2))
  m = jnp.where(ok[:, None, None], m, 0.0)
  r0, r1 = m[:, 0], m[:, 1]
  a = jnp.sum(r0 * r0, -1) + LOW_PASS
  b = jnp.sum(r0 * r1, -1)
  c = jnp.sum(r1 * r1, -1) + LOW_PASS
  # det(M M^T + s I) via |r0 x r1|^2 (Cauchy-Binet): a sum of squares, so a
  # thin needle cannot make it negative through cancellation in ac - b^2.
  cross = jnp.cross(r0, r1)
  det = (jnp.sum(cross * cross, -1) + LOW_PASS * (a + c - 2 * LOW_PASS)
         + LOW_PASS * LOW_PASS)
  opac = act.opacities
  valid = ok & (det > 0) & (opac >= ALPHA_THRESHOLD)
  det_s = jnp.where(valid, det, 1.0)
  conics = jnp.stack([c / det_s, -b / det_s, a / det_s], -1)
  means2d = jnp.stack([fx * x_s / z_s + cx, fy * y_s / z_s + cy], -1)

  # alpha = opacity * exp(-power) >= 1/255 exactly inside the ellipse
  # d^T Sigma^-1 d <= 2 log(255 opacity), whose bounding box has half-sides
  # sqrt(2 log(255 opacity) Sigma_xx) and sqrt(... Sigma_yy).
  level = 2.0 * jnp.log(jnp.maximum(opac / ALPHA_THRESHOLD, 1.0))
  half = numerics.safe_sqrt(level[:, None] * jnp.stack([a, c], -1))
  extents = jax.lax.stop_gradient(jnp.where(
      valid[:, None], half * (1 + _EXTENT_SLACK[0]) + _EXTENT_SLACK[1], 0.0))

  center = camera_lib.camera_center(cam, jnp).astype(dtype)
  dirs = numerics.safe_normalize(act.means - center)
  colors = sh.to_color(params.sh_dc, params.sh_rest, dirs, sh_degree)
  return Projected(
      means2d=means2d, conics=conics, depths=jnp.where(valid, z, 0.0),
      colors=colors, opacities=jnp.where(valid, opac, 0.0), extents=extents,
      valid=valid)
