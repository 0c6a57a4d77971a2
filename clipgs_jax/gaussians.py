"""Gaussian parameters (unconstrained, fixed capacity) and their activation."""

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import numerics
from clipgs_jax import sh


@flax.struct.dataclass
class GaussianParams:
  """Learnable parameters of C Gaussian slots, in unconstrained space.

  Attributes:
    means: float [C, 3], centres in world coordinates.
    log_scales: float [C, 3], log standard deviations along the local axes.
    quats: float [C, 4], rotation quaternions (w, x, y, z), not normalised;
      normalised where used, and a zero quaternion means identity.
    opacity_logits: float [C], opacity = sigmoid(logit).
    sh_dc: float [C, 3], degree-0 SH coefficients.
    sh_rest: float [C, K, 3], higher SH bands, K = (degree + 1)^2 - 1.
  """
  means: Any
  log_scales: Any
  quats: Any
  opacity_logits: Any
  sh_dc: Any
  sh_rest: Any

  @property
  def capacity(self) -> int:
    return self.means.shape[0]

  @property
  def sh_degree(self) -> int:
    return sh.degree_of(self.sh_rest.shape[1])


@flax.struct.dataclass
class Activated:
  """Constrained values from `activate`: float [C, 3], [C, 3, 3], [C]."""
  means: Any
  scales: Any
  rotations: Any
  opacities: Any


def quat_to_rotmat(quats: jax.Array) -> jax.Array:
  """float [..., 3, 3] rotation matrices from (w, x, y, z) quaternions.

  The quaternion is normalised first; a zero quaternion gives the identity
  (with zero gradient), never NaN.
  """
  q = numerics.safe_normalize(quats)
  # A zero quaternion normalises to zero; use the identity quaternion there.
  is_zero = jnp.all(q == 0, axis=-1, keepdims=True)
  q = jnp.where(is_zero, jnp.array([1.0, 0.0, 0.0, 0.0], q.dtype), q)
  w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
  rows = [
      [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ]
  return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def activate(params: GaussianParams) -> Activated:
  """The one place unconstrained parameters become physical quantities."""
  return Activated(
      means=params.means,
      scales=numerics.safe_exp(params.log_scales),
      rotations=quat_to_rotmat(params.quats),
      opacities=jax.nn.sigmoid(params.opacity_logits))


def validate(params: GaussianParams, alive, name: str = "params") -> None:
  """Raises ValueError unless shapes and dtypes form a consistent state."""
  if not isinstance(params, GaussianParams):
    raise ValueError(f"{name} must be a GaussianParams, got "
                     f"{type(params).__name__}.")
  c = np.shape(params.means)[0] if np.ndim(params.means) else -1
  k = np.shape(params.sh_rest)[1] if np.ndim(params.sh_rest) == 3 else -1
  expected = {"means": (c, 3), "log_scales": (c, 3), "quats": (c, 4),
              "opacity_logits": (c,), "sh_dc": (c, 3), "sh_rest": (c, k, 3)}
  for field, shape in expected.items():
    value = getattr(params, field)
    if np.shape(value) != shape or c < 0 or k < 0:
      raise ValueError(
          f"{name}.{field} has shape {np.shape(value)}, expected {shape} "
          f"(capacity C = {c} from means [C, 3]).")
    if not jnp.issubdtype(jnp.result_type(value), jnp.floating):
      raise ValueError(f"{name}.{field} must be floating point, got "
                       f"{jnp.result_type(value)}.")
  if k not in (0, 3, 8, 15):
    raise ValueError(f"{name}.sh_rest has {k} coefficients per channel; "
                     "expected 0, 3, 8 or 15 (SH degree 0-3).")
  if np.shape(alive) != (c,) or jnp.result_type(alive) != jnp.bool_:
    raise ValueError(f"alive must be bool [{c}], got "
                     f"{jnp.result_type(alive)} {np.shape(alive)}.")


def empty(capacity: int, sh_degree: int, dtype=jnp.float32
          ) -> tuple[GaussianParams, jax.Array]:
  """All-dead state of the given capacity: zero params and alive = False."""
  k = sh.num_rest_coeffs(sh_degree)
  params = GaussianParams(
      means=jnp.zeros((capacity, 3), dtype),
      log_scales=jnp.zeros((capacity, 3), dtype),
      quats=jnp.zeros((capacity, 4), dtype).at[:, 0].set(1),
      opacity_logits=jnp.zeros((capacity,), dtype),
      sh_dc=jnp.zeros((capacity, 3), dtype),
      sh_rest=jnp.zeros((capacity, k, 3), dtype))
  return params, jnp.zeros((capacity,), bool)
