"""Real spherical harmonics (degree 0-3) for view-dependent colour."""

import jax
import jax.numpy as jnp
import numpy as np

MAX_DEGREE = 3

# Normalisation constants of the real SH basis, Y_l^m, in the ordering and
# sign convention of the 3DGS PLY format (so exported files interoperate).
_C0 = 0.28209479177387814          # 1 / (2 sqrt(pi))
_C1 = 0.4886025119029199           # sqrt(3 / (4 pi))
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
       -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
       0.3731763325901154, -0.4570457994644658, 1.445305721320277,
       -0.5900435899266435)

# Rendered colour is SH + 0.5 (so zero coefficients give mid grey), clamped
# at 0; there is no upper clamp, as in the reference rasterizer.
COLOR_OFFSET = 0.5


def active_degree(step: jax.Array, every: int, max_degree: int
                  ) -> jax.Array:
  """int32 [], the SH degree trained at `step`: one more band every `every`
  steps (3DGS: 1000), capped at `max_degree`."""
  return jnp.minimum(jnp.asarray(step, jnp.int32) // max(every, 1),
                     max_degree)


def num_rest_coeffs(degree: int) -> int:
  """Number of non-DC coefficients per channel for an SH degree."""
  if not 0 <= degree <= MAX_DEGREE:
    raise ValueError(f"SH degree must be in [0, {MAX_DEGREE}], got {degree}.")
  return (degree + 1) ** 2 - 1


def degree_of(num_rest: int) -> int:
  """Inverse of `num_rest_coeffs`."""
  for d in range(MAX_DEGREE + 1):
    if num_rest_coeffs(d) == num_rest:
      return d
  raise ValueError(f"{num_rest} is not a valid number of rest SH "
                   "coefficients (expected 0, 3, 8 or 15).")


def rgb_to_dc(rgb):
  """DC coefficient that renders as `rgb` (inverse of the DC term + 0.5)."""
  return (rgb - COLOR_OFFSET) / _C0


def basis(dirs: jax.Array, degree: int) -> jax.Array:
  """float [..., (degree+1)^2], the real SH basis at unit directions."""
  x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
  out = [jnp.full_like(x, _C0)]
  if degree >= 1:
    out += [-_C1 * y, _C1 * z, -_C1 * x]
  if degree >= 2:
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out += [_C2[0] * xy, _C2[1] * yz, _C2[2] * (2 * zz - xx - yy),
            _C2[3] * xz, _C2[4] * (xx - yy)]
  if degree >= 3:
    out += [_C3[0] * y * (3 * xx - yy), _C3[1] * xy * z,
            _C3[2] * y * (4 * zz - xx - yy),
            _C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            _C3[4] * x * (4 * zz - xx - yy), _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3 * yy)]
  return jnp.stack(out, axis=-1)


def band_mask(num_rest: int, active_degree: jax.Array) -> jax.Array:
  """float [num_rest], 1 for rest coefficients of bands <= active_degree.

  `active_degree` may be traced, so raising it during training does not
  recompile anything.
  """
  band = np.concatenate([np.full(2 * l + 1, l) for l in range(1, 4)])
  return (jnp.asarray(band[:num_rest]) <= active_degree).astype(jnp.float32)


def to_color(sh_dc: jax.Array, sh_rest: jax.Array, dirs: jax.Array,
             active_degree: jax.Array | int) -> jax.Array:
  """float [N, 3] RGB from SH coefficients seen along unit `dirs`.

  Args:
    sh_dc: float [N, 3], degree-0 coefficients.
    sh_rest: float [N, K, 3], higher bands, K in {0, 3, 8, 15}.
    dirs: float [N, 3], unit viewing directions (camera centre to Gaussian).
    active_degree: int [], bands above it are ignored.
  """
  num_rest = sh_rest.shape[-2]
  degree = degree_of(num_rest)
  b = basis(dirs, degree)                                   # [N, (d+1)^2]
  color = b[..., :1] * sh_dc
  if num_rest:
    w = b[..., 1:] * band_mask(num_rest, active_degree).astype(b.dtype)
    color = color + jnp.einsum("nk,nkc->nc", w, sh_rest)
  return jnp.maximum(color + COLOR_OFFSET, 0.0)
