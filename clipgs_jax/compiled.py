"""The compiled part of a config: the fields that compiled code reads.

The jitted step, densify and prune functions are cached by it
(`cache_by_compiled_part`), so runs whose configs differ only in host
settings (a table's vanilla and clean rows; two runs that differ in tau)
share one compiled program instead of compiling the same program again.
"""

import dataclasses
import functools

from clipgs_jax.config import Config


class _HostOnly:
  """Stands in for a config field that compiled code must not read.

  Arithmetic, attribute access and truth tests on it raise, so a traced
  function that starts reading such a field fails at trace time instead of
  silently using one run's value for all the runs that share its program.
  """

  def __bool__(self):
    raise TypeError("a host-only config field was read by compiled code; "
                    "remove it from compiled.py's dropped fields")

  def __repr__(self):
    return "HOST_ONLY"


HOST_ONLY = _HostOnly()
# Fields that only the host loop reads: when to log, evaluate and checkpoint,
# the seed (it makes the initial PRNG key, which the state carries), the
# scene and split, and the test metrics.
_HOST_TRAIN_FIELDS = ("seed", "log_every", "eval_every", "checkpoint_every")
# Fields, by section, that the train step does not read: the prune rule (its
# own jitted function, guidance.prune), and what builds the scorer
# (guidance.make_scorer), which the step gets as an argument, and the
# classifier's construction (learned.init).
NOT_IN_STEP = {
    "semantic": ("prune", "tau", "n_min", "alpha_min", "rare_needs_evidence",
                 "prune_harm", "prune_start", "prune_every",
                 "max_prune_fraction", "static_prompts", "clip_variant",
                 "dense_input_size", "oracle_saturation"),
    "pixel": ("tau_p",),
    "residual": ("features",),
    # The classifier's sizes are its arrays' shapes; the features are the
    # scorer's.
    "learned": ("net", "dims", "hidden", "frequencies"),
}


def compiled_part(cfg: Config, dropped: dict[str, tuple[str, ...]] = {}  # pylint: disable=dangerous-default-value
                  ) -> Config:
  """`cfg` with the fields its compiled functions do not read as HOST_ONLY.

  Dropped: data, eval, the host fields of train, and the `dropped` fields
  of other sections (NOT_IN_STEP for the train step).
  """
  sections = {name: dataclasses.replace(
      getattr(cfg, name), **dict.fromkeys(fields, HOST_ONLY))
              for name, fields in dropped.items()}
  return dataclasses.replace(
      cfg, data=HOST_ONLY, eval=HOST_ONLY,
      train=dataclasses.replace(
          cfg.train, **dict.fromkeys(_HOST_TRAIN_FIELDS, HOST_ONLY)),
      **sections)


def cache_by_compiled_part(dropped: dict[str, tuple[str, ...]] = {}):  # pylint: disable=dangerous-default-value
  """Decorator factory: caches `make(cfg)` by `compiled_part(cfg, ...)`.

  `make` receives the compiled part; `.cache_clear()` works as for
  functools.lru_cache.
  """
  def decorate(make):
    cached = functools.lru_cache(maxsize=None)(make)

    @functools.wraps(make)
    def wrapper(cfg: Config):
      return cached(compiled_part(cfg, dropped))

    wrapper.cache_clear = cached.cache_clear
    return wrapper
  return decorate
