"""Per-field Adam (optax.partition) and helpers on its per-field moments."""

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from clipgs_jax import config as config_lib
from clipgs_jax import gaussians
from clipgs_jax import state as state_lib

FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc",
          "sh_rest")


def means_lr(step: jax.Array | int, cfg: config_lib.OptimConfig,
             extent: float, total_steps: int) -> jax.Array:
  """float [], the means learning rate after `step` updates.

  Log-linear from means_lr_init to means_lr_final over the decay length
  (means_lr_steps, or total_steps when that is 0), then constant; both ends
  are multiplied by the scene extent, so the step size is in scene units
  relative to the scene's size (3DGS).
  """
  length = cfg.means_lr_steps or total_steps
  t = jnp.clip(jnp.asarray(step, jnp.float32) / max(length, 1), 0.0, 1.0)
  log_lr = ((1.0 - t) * np.log(cfg.means_lr_init)
            + t * np.log(cfg.means_lr_final))
  return jnp.exp(log_lr) * extent


def _labels() -> gaussians.GaussianParams:
  # Each field is its own partition, named after the field.
  return gaussians.GaussianParams(**{f: f for f in FIELDS})


def make(cfg: config_lib.OptimConfig, extent: float, total_steps: int
         ) -> optax.GradientTransformation:
  """Adam per GaussianParams field with the 3DGS learning rates.

  Args:
    cfg: learning rates and Adam constants.
    extent: scene extent (camera-centre radius x 1.1); scales the means LR.
    total_steps: length of the run, the default means-LR decay length.
  """
  if not extent > 0:
    raise ValueError(f"optim.make: extent must be positive, got {extent}; "
                     "set Config.scene_extent or load a scene.")
  def adam(lr: float | Callable) -> optax.GradientTransformation:
    return optax.adam(lr, b1=cfg.adam_b1, b2=cfg.adam_b2, eps=cfg.adam_eps)
  schedule = lambda count: means_lr(count, cfg, extent, total_steps)
  transforms = {
      "means": adam(schedule),
      "log_scales": adam(cfg.log_scales_lr),
      "quats": adam(cfg.quats_lr),
      "opacity_logits": adam(cfg.opacity_lr),
      "sh_dc": adam(cfg.sh_dc_lr),
      "sh_rest": adam(cfg.sh_rest_lr),
  }
  return optax.partition(transforms, _labels())


def for_run(cfg: config_lib.Config) -> optax.GradientTransformation:
  """The run's optimizer: `make` with its learning rates, scene extent
  (the means' schedule) and step count."""
  return make(cfg.optim, cfg.scene_extent, cfg.train.steps)


def apply(state: state_lib.TrainState, grads: gaussians.GaussianParams,
          cfg: config_lib.Config, batch_size: int = 1):
  """One Adam step of the train state on the summed gradients of a batch.

  Dead rows get no gradient from the render; the mask makes it explicit.
  The gradient is that of the batch's mean loss (the sum over its
  `batch_size` views divided by it; B = 1 divides by nothing).

  Returns:
    (params, opt_state, metrics): the updated parameters and Adam state,
    and "grad_norm/<field>" of the masked mean gradient.
  """
  def masked(g):
    g = g if batch_size == 1 else g / batch_size
    return jnp.where(state.alive.reshape((-1,) + (1,) * (g.ndim - 1)), g, 0.0)
  grads = jax.tree.map(masked, grads)
  updates, opt_state = for_run(cfg).update(grads, state.opt_state, state.params)
  params = optax.apply_updates(state.params, updates)
  metrics = {f"grad_norm/{field}": optax.tree.norm(getattr(grads, field))
             for field in FIELDS}
  return params, opt_state, metrics


def zero_field(opt_state, field: str, capacity: int) -> optax.OptState:
  """Zeroes the Adam moments of one GaussianParams field for every row."""
  if field not in FIELDS:
    raise ValueError(f"optim.zero_field: unknown field {field!r}; one of "
                     f"{FIELDS}.")
  inner = dict(opt_state.inner_states)
  inner[field] = state_lib.map_rows(inner[field], capacity, jnp.zeros_like)
  return opt_state._replace(inner_states=inner)


def moments(opt_state, field: str) -> tuple[jax.Array, jax.Array]:
  """(mu, nu) of one field: float arrays shaped like that parameter."""
  adam_state = opt_state.inner_states[field].inner_state[0]
  return (getattr(adam_state.mu, field), getattr(adam_state.nu, field))


def count(opt_state) -> jax.Array:
  """int32 [], the number of updates applied (from the means Adam state)."""
  return opt_state.inner_states["means"].inner_state[0].count
