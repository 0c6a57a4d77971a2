"""The training state and every operation on its rows.

A `TrainState` holds a fixed capacity C of Gaussian slots: the parameters,
an `alive` mask, Adam's moments and two per-row statistics (densification
and semantic), all with a leading axis C. Every operation that changes
which Gaussian a row holds (clone, split, prune, capacity growth) goes
through `apply_rows`, which edits the parameters, the alive mask, Adam's
mu/nu and every per-row statistic together, so they cannot drift apart.
Rows that receive a new Gaussian start with zero moments and zero
statistics.
"""

from typing import Any, Callable

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from clipgs_jax import gaussians
from clipgs_jax import tree_util


@flax.struct.dataclass
class DensifyStats:
  """What densification decides on, accumulated since the last densify.

  Attributes:
    grad_accum: float [C], sum over views of |d loss / d NDC xy|.
    denom: float [C], number of views whose image the splat overlapped.
    max_radius: float [C], largest screen radius (pixels) seen.
  """
  grad_accum: Any
  denom: Any
  max_radius: Any

  @classmethod
  def zeros(cls, capacity: int) -> "DensifyStats":
    # Separate buffers: one shared array could not be donated three times.
    z = lambda: jnp.zeros((capacity,), jnp.float32)
    return cls(grad_accum=z(), denom=z(), max_radius=z())


@flax.struct.dataclass
class SemanticStats:
  """CLIP-GS per-Gaussian evidence statistics (paper eqs. 8-10).

  Attributes:
    acc: float [C], accumulated weight * beta * max(0, s_hat_d - 0.5).
    weight: float [C], accumulated weight; s_j = acc / weight. Equal to n
      under the paper's visibility weighting.
    n: float [C], number of scored views in which the Gaussian contributed
      (the n_j of the eq. 13 visibility rule, whatever the weighting).
  """
  acc: Any
  weight: Any
  n: Any

  @classmethod
  def zeros(cls, capacity: int) -> "SemanticStats":
    z = lambda: jnp.zeros((capacity,), jnp.float32)
    return cls(acc=z(), weight=z(), n=z())


@flax.struct.dataclass
class TrainState:
  """Everything that changes during training.

  Attributes:
    params: GaussianParams with capacity C.
    alive: bool [C], slots in use.
    opt_state: optax state of `optim.make` (per-field Adam).
    densify: DensifyStats, per row, since the last densification.
    semantic: SemanticStats, per row, CLIP-GS evidence statistics.
    step: int32 [], finished optimisation steps.
    key: PRNG key of the run; constant, per-step keys come from fold_in.
    maps: the transient map's running statistics (residual.ResidualState)
      when the map is the residual map, else None; fixed in size.
  """
  params: gaussians.GaussianParams
  alive: jax.Array
  opt_state: Any
  densify: DensifyStats
  semantic: SemanticStats
  step: jax.Array
  key: jax.Array
  maps: Any = None

  @property
  def capacity(self) -> int:
    return self.alive.shape[0]


def is_row_leaf(x, capacity: int) -> bool:
  """True for arrays with one row per Gaussian slot (leading axis C).

  In the optimizer state these are exactly Adam's mu and nu; the step
  counts are scalars.
  """
  return np.ndim(x) >= 1 and np.shape(x)[0] == capacity


def map_rows(opt_state, capacity: int, fn: Callable) -> optax.OptState:
  """Applies fn to every per-row leaf (Adam moments) of an optimizer state."""
  return jax.tree.map(
      lambda x: fn(x) if is_row_leaf(x, capacity) else x, opt_state)


def apply_rows(state: TrainState, *, params_fn: Callable,
               alive_fn: Callable, fresh_fn: Callable) -> TrainState:
  """The one helper every row operation goes through.

  Args:
    state: the state to edit.
    params_fn: GaussianParams -> GaussianParams.
    alive_fn: bool [C] -> bool [C'].
    fresh_fn: applied to every Adam moment and every per-row statistic
      (densify and semantic); it must give the touched rows zeros.
  """
  capacity = state.alive.shape[0]
  return state.replace(
      params=params_fn(state.params),
      alive=alive_fn(state.alive),
      opt_state=map_rows(state.opt_state, capacity, fresh_fn),
      densify=jax.tree.map(fresh_fn, state.densify),
      semantic=jax.tree.map(fresh_fn, state.semantic))


def write_rows(state: TrainState, idx: jax.Array,
               values: gaussians.GaussianParams | None,
               alive: bool | jax.Array) -> TrainState:
  """Rows idx get `values` (None: keep) and `alive`; moments/stats become 0.

  Out-of-range indices (the fill value C of a sized nonzero) write nothing.
  """
  params_fn = ((lambda p: p) if values is None
               else lambda p: tree_util.tree_index_set(p, idx, values))
  return apply_rows(
      state, params_fn=params_fn,
      alive_fn=lambda a: a.at[idx].set(alive, mode="drop"),
      fresh_fn=lambda x: x.at[idx].set(0, mode="drop"))


def resize(state: TrainState, capacity: int) -> TrainState:
  """Host-side: the same state with `capacity` slots (new slots dead, zero).

  Growing C changes every array shape, so the jitted train step and
  densify recompile once afterwards. Shrinking is refused when it would cut
  off alive rows.
  """
  old = state.alive.shape[0]
  if capacity < old and bool(jnp.any(state.alive[capacity:])):
    raise ValueError(f"state.resize: cannot shrink capacity {old} to "
                     f"{capacity}: alive rows would be lost; compact first.")
  def fit(x, fill=0):
    if capacity <= old:
      return x[:capacity]
    pad = jnp.full((capacity - old,) + x.shape[1:], fill, x.dtype)
    return jnp.concatenate([x, pad])
  empty, _ = gaussians.empty(max(capacity - old, 0), state.params.sh_degree)
  def params_fn(p):
    if capacity <= old:
      return jax.tree.map(lambda x: x[:capacity], p)
    return jax.tree.map(lambda x, e: jnp.concatenate([x, e.astype(x.dtype)]),
                        p, empty)
  return apply_rows(state, params_fn=params_fn,
                    alive_fn=lambda a: fit(a, False), fresh_fn=fit)
