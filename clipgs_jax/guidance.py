"""CLIP-GS semantic guidance inside training: scorers, schedule and pruning.

The equations are the pure functions of `semantic.py`; this module decides
when they run (SemanticConfig's schedule), what scores a view (a scorer),
and applies the prune through `state.write_rows`, so parameters, Adam
moments and every per-row statistic move together.

A scorer is a pytree with a method `score(image, view) -> {"s_hat_d",
"s_hat_s"}` (float32 scalars; s_hat_s is NaN when the scorer has no static
prompts, and any other NaN stops training). It is passed to the jitted
train step as its own argument, so frozen CLIP weights are an input of the
step, never part of the trained state:
  - `OracleScorer` (benchmarks only): the ground-truth transient mask of the
    training view through `semantic.oracle_score`; no static score.
  - `clip.scorer.ClipScorer` (the paper): the Flax CLIP tower on the
    rendered view. It lives in the clip package and is imported only when
    the config asks for it, so runs without CLIP never import it.

With pixel evidence (SemanticConfig.evidence = "pixel") the scorer is a
`PixelMapScorer`: one float [H, W] map m per training view, the probability
that each pixel shows a transient. The train step hands m[view] to the
rasterizer, which returns each Gaussian's sum_i w_ij m_i in the same pass
(`semantic.accumulate_pixel`). Maps come from the training photo, not the
render: the photo shows the transient whether or not it has been fitted
yet, the map must exist before the render that accumulates it, and a
frozen scorer on a fixed photo needs to run once per view, not per step.
  - ORACLE-PIXEL (benchmarks only): m = the ground-truth transient mask.
  - dense CLIP: `clip.scorer.make_dense` per patch, upsampled to the view.
"""

import functools
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import compiled
from clipgs_jax import config as config_lib
from clipgs_jax import densify
from clipgs_jax import guidance_config
from clipgs_jax import semantic
from clipgs_jax import state as state_lib
from clipgs_jax.data import canvas
from clipgs_jax.maps import sources

# Keys of the per-step scores in the train step's metrics: image evidence
# logs the view's scores, pixel evidence the mean of the view's map. Beside
# them the step logs "view" and "scored" (bool: the step scored its view;
# the values of other steps are placeholders).
SCORE_KEYS = ("s_hat_d", "s_hat_s")
MAP_KEYS = ("map_mean",)
# Scores a scorer may lack (NaN, logged as None): s_hat_s needs static
# prompts. Any other non-finite score on a scored step is an error.
OPTIONAL_SCORE_KEYS = ("s_hat_s",)


def per_step_value_keys(sem: guidance_config.SemanticConfig) -> tuple[str, ...]:
  """The per-step scores that fit logs for each scored step."""
  return MAP_KEYS if sem.localized else SCORE_KEYS


def per_step_keys(sem: guidance_config.SemanticConfig) -> tuple[str, ...]:
  """Every per-step key of the train step's metrics (scores.jsonl), kept
  out of the training log."""
  return per_step_value_keys(sem) + ("view", "scored")


# ORACLE-PATCH pools the masks to the patch grid of dense CLIP's input:
# ViT-B/32's patch side in pixels (dense_input_size 448 -> a 14x14 grid).
ORACLE_PATCH_SIZE = 32

# Bins of the s_j histogram logged at each prune event, over [0, beta / 2]
# for image evidence (s_j is a mean of beta * max(0, s_hat_d - 0.5) <=
# beta / 2) and over [0, 1] for pixel evidence (s_j is a probability).
HISTOGRAM_BINS = 50


@flax.struct.dataclass
class PixelMapScorer:
  """Per-pixel transient probability maps of the training views.

  Attributes:
    maps: float32 [V, H, W] in [0, 1], one map per training view (0 outside
      a photo on a larger canvas).
  """
  maps: jax.Array
  per_view = ("maps",)     # fields with one entry per view (sharding.py)

  def score_map(self, view: jax.Array) -> jax.Array:
    """float32 [H, W], the map of training view `view`."""
    return self.maps[view]


@flax.struct.dataclass
class OracleScorer:
  """Scores a training view from its ground-truth transient mask.

  Not the paper's method: a perfect image-level detector, for benchmarks,
  labelled "oracle" in every output. See `semantic.oracle_score`.

  Attributes:
    masks: bool [V, H, W], True = transient pixel, per training view.
    saturation: area fraction at which the score reaches 1.
    areas: float32 [V], each photo's pixels when the photos lie on a
      larger canvas (the area fraction is of the photo), else None.
  """
  masks: jax.Array
  saturation: float = flax.struct.field(pytree_node=False)
  areas: jax.Array | None = None
  per_view = ("masks", "areas")

  def score(self, image: jax.Array, view: jax.Array) -> dict[str, jax.Array]:
    del image  # a perfect detector does not need to look
    area = None if self.areas is None else self.areas[view]
    return {"s_hat_d": semantic.oracle_score(self.masks[view],
                                             self.saturation, area),
            "s_hat_s": jnp.float32(jnp.nan)}


def make_scorer(cfg: config_lib.Config, scene, *,
                clip_weights: str | None = None,
                clip_params: tuple[Any, dict] | None = None):
  """The scorer `cfg.semantic` asks for, or None when guidance is off.

  Args:
    cfg: the checked config (config_file.check): its semantic section and,
      for the residual map, its residual section. Guidance off (scorer
      "off") returns None and imports nothing.
    scene: a data.scene.Scene; the oracle reads `scene.train.masks`.
    clip_weights: the --clip_weights flag (else $CLIPGS_CLIP_WEIGHTS).
    clip_params: (ClipConfig, params) to use instead of a weights file
      (benchmarks with random weights, tests).
  """
  sem = cfg.semantic
  if not sem.enabled:
    return None
  if sem.scorer in ("residual", "learned"):
    source = _residual_source(None, cfg.residual, scene)
    if sem.scorer == "residual":
      return source
    return source.replace(pixel_features=sources.learned_features(
        scene.train.images, cfg.learned, getattr(scene.train, "sizes",
                                                 None)))
  if sem.scorer in ("oracle", "uniform", "oracle_patch"):
    masks = scene.train.masks
    if masks is None:
      raise ValueError(
          f"semantic scorer {sem.scorer!r} reads ground-truth transient "
          "masks, but this scene has none: add masks/<image stem>.png (white "
          "= transient) for the training views, or use "
          "--config.semantic.scorer=clip|off.")
    sizes = getattr(scene.train, "sizes", None)
    if sem.scorer == "uniform":
      return uniform_control(masks, sizes)
    if sem.scorer == "oracle_patch":
      grid = sem.dense_input_size // ORACLE_PATCH_SIZE
      maps = (sources.oracle_patch_maps(masks, grid) if sizes is None
              else jnp.asarray(per_photo(
                  lambda m: sources.oracle_patch_maps(m[None], grid)[0],
                  masks, sizes)))
      return _pixel_source(maps, cfg.residual, scene)
    if sem.localized:
      return PixelMapScorer(maps=jnp.asarray(masks, jnp.float32))
    return OracleScorer(
        masks=jnp.asarray(masks, bool), saturation=sem.oracle_saturation,
        areas=None if sizes is None else jnp.asarray(
            np.prod(sizes, axis=-1), jnp.float32))
  # Only here is CLIP imported.
  from clipgs_jax.clip import scorer as clip_scorer  # pylint: disable=g-import-not-at-top
  from clipgs_jax.clip import weights  # pylint: disable=g-import-not-at-top
  if clip_params is None:
    clip_params = weights.load(weights.resolve_weights_path(clip_weights),
                               sem.clip_variant)
  if sem.localized:
    dense = clip_scorer.make_dense(sem, clip_params,
                                   input_size=sem.dense_input_size)
    return _pixel_source(
        dense_maps(dense, scene.train.images,
                   getattr(scene.train, "sizes", None)), cfg.residual, scene)
  return clip_scorer.make(sem, clip_params)


def _pixel_source(maps: jax.Array, rc: guidance_config.ResidualConfig, scene):
  """A semantic map per view: as it is, or gating the residual map."""
  if rc.with_semantic:
    return _residual_source(maps, rc, scene)
  return PixelMapScorer(maps=maps)


def _residual_source(maps, rc: guidance_config.ResidualConfig,
                     scene) -> sources.ResidualSource:
  """The residual map's scorer, with the photos' feature regions when
  rc.features names a backbone."""
  if not rc.features:
    return sources.ResidualSource(semantic=maps)
  labels, num = sources.feature_regions(
      scene.train.images, rc.features, getattr(scene.train, "sizes", None))
  return sources.ResidualSource(semantic=maps, labels=labels,
                                num_regions=num)


def per_photo(fn, arrays, sizes, fill=0) -> np.ndarray:
  """fn on each view's photo, put back on the canvas (`fill` outside).

  Args:
    fn: [h, w, ...] -> [h, w, ...].
    arrays: [V, H, W, ...] on the views' canvas.
    sizes: data.scene.Views.sizes: int [V, 2] photo sizes, or None (each
      view's array whole).
  """
  if sizes is None:
    return np.stack([np.asarray(fn(a)) for a in arrays])
  return canvas.on_canvas(
      [np.asarray(fn(a[:h, :w])) for a, (w, h) in zip(arrays, sizes)],
      sizes, fill)


def uniform_control(masks, sizes=None) -> PixelMapScorer:
  """The control for localized evidence: no location, the same total.

  Every pixel of every view gets the masks' mean transient fraction, so the
  accumulated s_j is (nearly) that constant for every Gaussian: the opacity
  loss of eqs. 11-12 becomes a uniform opacity penalty of ORACLE-PIXEL's
  average strength, and tau_p never fires. What a localized row gains over
  this row is what the location of the evidence buys.

  Args:
    masks: bool [V, H, W], the training views' ground-truth masks.
    sizes: int [V, 2] of photos on a larger canvas (data.scene.Views.sizes)
      or None; the fraction is of the photos' pixels, 0 outside them.
  """
  masks = np.asarray(masks, bool)
  if sizes is None:
    fraction = float(np.mean(masks))
    return PixelMapScorer(maps=jnp.full(np.shape(masks), fraction,
                                        jnp.float32))
  inside = per_photo(lambda m: np.ones(m.shape, bool), masks, sizes, False)
  fraction = float(np.sum(masks) / np.sum(inside))
  return PixelMapScorer(maps=jnp.asarray(inside * fraction, jnp.float32))


def dense_maps(dense_scorer, images, sizes=None) -> jax.Array:
  """float32 [V, H, W]: a dense scorer's map of every training photo.

  Args:
    dense_scorer: an object with `score_map(image, view) -> [H, W]`.
    images: float [V, H, W, 3] in [0, 1], the training photos.
    sizes: int [V, 2] of photos on a larger canvas (data.scene.Views.sizes)
      or None: each photo is scored alone, its map 0 outside it.
  """
  fn = jax.jit(lambda im: dense_scorer.score_map(im, jnp.int32(0)))
  maps = per_photo(lambda im: fn(jnp.asarray(im, jnp.float32)), images,
                   sizes)
  return jnp.asarray(maps, jnp.float32)


def check_scorer(sem: guidance_config.SemanticConfig, scorer,
                 caller: str) -> None:
  """Raises unless a scorer is given exactly when `sem` is enabled."""
  if (scorer is not None) != sem.enabled:
    raise ValueError(
        f"{caller}: semantic scorer {sem.scorer!r} with "
        f"{len(sem.distractor_prompts)} distractor prompts "
        f"{'needs a' if sem.enabled else 'takes no'} scorer; build it with "
        "guidance.make_scorer(cfg, scene).")


def scores_due(step: jax.Array,
               sem: guidance_config.SemanticConfig) -> jax.Array:
  """bool []: the step that starts at `step` finished steps scores its view."""
  since = step - sem.accumulate_start
  return (since >= 0) & (since % sem.score_every == 0)


def opacity_regularizer(stats: state_lib.SemanticStats,
                        opacity_logits: jax.Array, alive: jax.Array,
                        step: jax.Array, cfg: config_lib.Config
                        ) -> jax.Array:
  """Eqs. 11-12 from reg_start on, 0 before and for reset_quiet steps
  after each opacity reset."""
  sem = cfg.semantic
  loss = semantic.opacity_loss(stats, opacity_logits, alive, sem.lambda_c)
  quiet = densify.since_reset_within(step, sem.reset_quiet, cfg)
  return jnp.where((step >= sem.reg_start) & ~quiet, loss, 0.0)


def score_and_accumulate(
    stats: state_lib.SemanticStats, image: jax.Array, visible: jax.Array,
    weight: jax.Array | None, view: jax.Array, step: jax.Array, scorer,
    sem: guidance_config.SemanticConfig
) -> tuple[state_lib.SemanticStats, dict[str, jax.Array]]:
  """Scores the rendered view when due and accumulates (eqs. 5-9).

  The scorer runs under `lax.cond`, so off-cadence steps skip it; their
  scores are 0 placeholders with "scored" False, and add nothing.

  Args:
    stats: per-row acc, weight and n.
    image: float [H, W, 3], the render used for the photometric loss.
    visible: bool [C], the Gaussians that contributed to the render.
    weight: None (visibility weighting) or float [C], each Gaussian's
      contribution to the render (sem.weighting; see semantic.accumulate).
    view: int32 [], the training view's index.
    step: int32 [], finished steps before this one.
    scorer: an object with `score(image, view)` (see module docstring).
    sem: the semantic config.
  Returns:
    (stats, {"s_hat_d", "s_hat_s", "scored": bool []}).
  """
  image = jax.lax.stop_gradient(jnp.clip(image, 0.0, 1.0))
  due = scores_due(step, sem)
  skipped = {k: jnp.float32(0.0) for k in SCORE_KEYS}
  scores = jax.lax.cond(
      due,
      lambda: {k: jnp.asarray(v, jnp.float32)
               for k, v in scorer.score(image, view).items()},
      lambda: skipped)
  stats = semantic.accumulate(stats, visible, scores["s_hat_d"], sem.beta,
                              weight, scored=due)
  return stats, scores | {"scored": due}


def prune_due(step: int, cfg: config_lib.Config) -> bool:
  """Host-side: prune after `step` finished steps (from prune_start on).

  Never after the last step, as densification (densify.due): what crossed
  tau since the last prune stays in the final model, down-weighted by the
  opacity loss, and `experiments/report.py --report=masks` can still show it.
  Held after a reset at R while R < step <= R + reset_quiet: the faint-row
  rule would read the reset's alpha, and the opacity loss is off there.
  """
  sem = cfg.semantic
  since = step - sem.prune_start
  quiet = densify.since_reset_within(step - 1, sem.reset_quiet, cfg)
  return (sem.enabled and sem.prune and 0 < step < cfg.train.steps
          and since >= 0 and since % sem.prune_every == 0 and not quiet)


def prune_thresholds(cfg: config_lib.Config,
                     tau: float | None = None) -> dict[str, float]:
  """semantic.prune_masks' thresholds for `cfg`: pixel.tau_p (pixel
  evidence) or semantic.tau, or `tau` when given (a preview of another
  threshold)."""
  sem = cfg.semantic
  if tau is None:
    tau = cfg.pixel.tau_p if sem.localized else sem.tau
  return {"tau": tau, "n_min": sem.n_min / sem.score_every,
          "alpha_min": sem.alpha_min,
          "min_weight": semantic.MIN_EVIDENCE_WEIGHT if sem.localized
                        else 0.0,
          "rare_needs_evidence": sem.rare_needs_evidence}


def prune_candidates(state: state_lib.TrainState, cfg: config_lib.Config
                     ) -> tuple[jax.Array, jax.Array]:
  """Eq. 13's two clauses on `state` under `cfg`'s thresholds, before the
  guard: (semantic, visibility), as semantic.prune_masks."""
  return semantic.prune_masks(
      state.semantic, state.params.opacity_logits, state.alive,
      **prune_thresholds(cfg))


def prune(state: state_lib.TrainState, spared: jax.Array | None = None, *,
          cfg: config_lib.Config
          ) -> tuple[state_lib.TrainState, dict[str, jax.Array]]:
  """Eq. 13: removes alive rows with s_j > tau, or n_j < n_min and
  alpha_j < alpha_min; their parameters, moments and statistics are cleared.

  n_min is divided by score_every: n counts scored views only, so scoring
  every k-th step makes n a 1/k sample of the views a Gaussian was seen in.

  With pixel evidence the threshold is tau_p on the probability s_j, for
  rows with at least semantic.MIN_EVIDENCE_WEIGHT of evidence. An event
  that would remove more than max_prune_fraction of the alive rows removes
  none (semantic.guard_prune). `spared` (bool [C] or None) rows stay out of
  the semantic clause (render_without.py).

  Returns:
    (state, info) with int32 num_alive_before, num_pruned_semantic,
    num_pruned_visibility (0 when guarded), num_refused (what a refused
    event would have removed, else 0), bool guarded, float32
    [HISTOGRAM_BINS] histogram of s_j over the alive rows before the prune
    (bins: histogram_edges), and bool [C] pruned_semantic, the rows the
    semantic rule removed (for the mask IoU of the pruned Gaussians).
  """
  sem = cfg.semantic
  by_score, by_visibility = prune_candidates(state, cfg)
  if spared is not None:
    by_score &= ~spared
  wanted = jnp.sum(by_score | by_visibility, dtype=jnp.int32)
  by_score, by_visibility, guarded = semantic.guard_prune(
      by_score, by_visibility, state.alive, sem.max_prune_fraction)
  s = semantic.normalized_scores(state.semantic)
  histogram, _ = jnp.histogram(s, bins=HISTOGRAM_BINS,
                               range=_histogram_range(sem),
                               weights=state.alive.astype(jnp.float32))
  capacity = state.alive.shape[0]
  rows = jnp.arange(capacity, dtype=jnp.int32)
  info = {
      "num_alive_before": jnp.sum(state.alive, dtype=jnp.int32),
      "num_pruned_semantic": jnp.sum(by_score, dtype=jnp.int32),
      "num_pruned_visibility": jnp.sum(by_visibility, dtype=jnp.int32),
      "num_refused": jnp.where(guarded, wanted, 0),
      "guarded": guarded,
      "histogram": histogram,
      "pruned_semantic": by_score,
  }
  state = state_lib.write_rows(
      state, jnp.where(by_score | by_visibility, rows, capacity), None,
      alive=False)
  return state, info


@compiled.cache_by_compiled_part()
def make_prune(cfg: config_lib.Config):
  """Jitted prune(state, spared) -> (state, info); the state is donated."""
  return jax.jit(functools.partial(prune, cfg=cfg), donate_argnums=(0,))


def _histogram_range(
    sem: guidance_config.SemanticConfig) -> tuple[float, float]:
  return (0.0, 1.0) if sem.localized else (0.0, 0.5 * sem.beta)


def histogram_edges(sem: guidance_config.SemanticConfig) -> list[float]:
  """The HISTOGRAM_BINS + 1 bin edges of the prune-event histogram."""
  return np.linspace(*_histogram_range(sem), HISTOGRAM_BINS + 1).tolist()


def summarize(prune_events: list[dict], num_alive: int,
              stats: state_lib.SemanticStats) -> dict[str, Any]:
  """The metrics.json fields of a run's semantic stage.

  fraction_pruned = Gaussians removed by eq. 13, both conditions (s_j > tau
  and the n_j / alpha_j visibility rule; the two counts are beside it) /
  (those removed + those alive at the end).
  """
  semantic_total = sum(e["num_pruned_semantic"] for e in prune_events)
  visibility_total = sum(e["num_pruned_visibility"] for e in prune_events)
  removed = semantic_total + visibility_total
  refused = [e for e in prune_events if e.get("guarded")]
  return {
      "num_pruned_semantic": semantic_total,
      "num_pruned_visibility": visibility_total,
      "fraction_pruned": removed / max(removed + num_alive, 1),
      "num_prune_events": len(prune_events),
      "num_refused_prune_events": len(refused),
      "refused_prune_steps": [e["step"] for e in refused],
      "semantic_bytes": semantic.state_bytes(stats),
  }
