"""Numerically safe primitives with finite values and gradients everywhere."""

import jax
import jax.numpy as jnp

# exp(88) is about 1.65e38, just under float32's max (3.4e38); clamping here
# keeps exp and its derivative finite for any input.
_MAX_EXP_ARG = 88.0


@jax.custom_jvp
def safe_exp(x: jax.Array) -> jax.Array:
  """exp(x) with the argument clamped at 88 so value and grad stay finite."""
  return jnp.exp(jnp.minimum(x, _MAX_EXP_ARG))


@safe_exp.defjvp
def _safe_exp_jvp(primals, tangents):
  (x,), (x_dot,) = primals, tangents
  y = safe_exp(x)
  # The derivative of the clamped function is the clamped value itself; the
  # clamp's own zero slope past 88 would hide a runaway parameter.
  return y, y * x_dot


def _tiny(dtype) -> jax.Array:
  # Smallest squared norm treated as non-zero: below it, 1/sqrt underflows
  # to inf in the backward pass.
  return jnp.asarray(jnp.finfo(dtype).tiny, dtype)


def safe_sqrt(x: jax.Array) -> jax.Array:
  """sqrt(max(x, 0)) with a zero (not inf) gradient at and below 0."""
  # Double where: the dead branch gets a safe input so its gradient is finite.
  positive = x > 0
  return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def safe_normalize(x: jax.Array, axis: int = -1) -> jax.Array:
  """x / |x| along `axis`; the zero vector maps to zero with zero gradient."""
  sq = jnp.sum(x * x, axis=axis, keepdims=True)
  nonzero = sq > _tiny(x.dtype)
  inv = jax.lax.rsqrt(jnp.where(nonzero, sq, 1.0))
  return jnp.where(nonzero, x * inv, 0.0)
