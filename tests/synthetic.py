"""Random Gaussian scenes and cameras for rasterizer tests."""

import jax.numpy as jnp
import numpy as np

from clipgs_jax import camera
from clipgs_jax import gaussians
from clipgs_jax import sh


def random_params(n, seed=0, degree=1, dtype=jnp.float32, spread=1.0,
                  log_scale=(-3.0, -1.5)):
  """n random Gaussians in a cube of half-side `spread` around the origin."""
  rng = np.random.default_rng(seed)
  k = sh.num_rest_coeffs(degree)
  return gaussians.GaussianParams(
      means=jnp.asarray(rng.uniform(-spread, spread, (n, 3)), dtype),
      log_scales=jnp.asarray(rng.uniform(*log_scale, (n, 3)), dtype),
      quats=jnp.asarray(rng.normal(size=(n, 4)), dtype),
      opacity_logits=jnp.asarray(rng.normal(size=n), dtype),
      sh_dc=jnp.asarray(rng.normal(size=(n, 3)) * 0.5, dtype),
      sh_rest=jnp.asarray(rng.normal(size=(n, k, 3)) * 0.1, dtype))


def front_camera(width=37, height=29, focal=40.0, distance=4.0,
                 dtype=np.float32):
  """A camera on the -z axis looking at the origin, world +y up."""
  return camera.look_at([0.0, 0.0, -distance], [0.0, 0.0, 0.0],
                        [0.0, 1.0, 0.0], focal, focal, width, height,
                        dtype=dtype)


def with_rows(params, **fields):
  """params with some fields replaced (numpy/list values are converted)."""
  return params.replace(**{
      k: jnp.asarray(v, params.means.dtype) for k, v in fields.items()})
