"""Frozen configuration dataclasses with the paper's and 3DGS's defaults.

`check` turns a config file's ConfigDict into a Config and is the one
place where a run's config is checked, before any scene or weights load.
"""

import dataclasses
import functools
import importlib.util
import os
import types
import typing

from absl import app
import ml_collections

from clipgs_jax import cli
from clipgs_jax import features
from clipgs_jax import metrics as metrics_lib
from clipgs_jax import residual
from clipgs_jax.data import default_scene
from clipgs_jax.data import scene as scene_lib


@dataclasses.dataclass(frozen=True)
class RenderConfig:
  """How the tile rasterizer projects, bins and blends.

  `tile_budget` sizes the intersection buffer: it holds num_tiles x
  tile_budget (tile, Gaussian) pairs, 4 bytes each, i.e. K is the *mean*
  list length a view may reach; one tile may hold any number of entries.
  A view with more intersections drops the farthest ones and counts them in
  `RenderOutput.num_overflow`, never silently. The sort itself runs on the
  smallest of a ladder of buffers that holds the view's real count.
  The blend's time follows the total list length, not the longest list:
  `lanes` tiles are blended side by side, `chunk_size` entries per round,
  each lane taking the next tile (longest first) when its tile ends.
  """
  near: float = 0.2            # near plane in scene units; closer is culled
  tile_budget: int = 2048      # K: buffer entries per tile, on average
  chunk_size: int = 32         # B: list entries blended per round per lane
  lanes: int = 0               # tiles blended side by side; 0 = tiles / 6
  # 8x8 tiles: a splat covers a larger share of a smaller tile, so the blend
  # evaluates fewer zero-alpha pixels. Bird ds4: 0.44 s/step over a 7k-step
  # run; its final state steps in 500-600 ms against 880-1,030 at 16x16
  # (BUILD_NOTES.md, "Rasterizer").
  tile_size: int = 8           # tile side in pixels


@dataclasses.dataclass(frozen=True)
class GaussiansConfig:
  """Capacity and initialisation of the Gaussian set."""
  capacity: int = 0            # initial slots C; 0 = auto: 2x init points, pow2
  min_capacity: int = 4096     # floor of the automatic capacity
  max_capacity: int = 1 << 20  # densification doubles C up to this, then stops
  sh_degree: int = 3           # highest SH degree stored and reached
  init_opacity: float = 0.1    # opacity of every initial Gaussian (3DGS)
  init_min_scale: float = 1e-4  # floor of the kNN scale, in scene units
  init_neighbors: int = 3      # scale = mean distance to this many neighbours
  random_init_points: int = 10_000  # used only when the scene has no points


@dataclasses.dataclass(frozen=True)
class OptimConfig:
  """Adam per parameter field; 3DGS learning rates."""
  means_lr_init: float = 1.6e-4   # x scene extent, at step 0
  means_lr_final: float = 1.6e-6  # x scene extent, at the end of the decay
  means_lr_steps: int = 0      # log-linear decay length; 0 = train.steps
  sh_dc_lr: float = 2.5e-3     # degree-0 SH coefficients
  sh_rest_lr: float = 2.5e-3 / 20  # higher SH bands: 20x lower than DC
  opacity_lr: float = 0.05     # on opacity logits
  log_scales_lr: float = 5e-3  # on log standard deviations
  quats_lr: float = 1e-3       # on raw quaternions
  adam_b1: float = 0.9         # Adam first-moment decay
  adam_b2: float = 0.999       # Adam second-moment decay
  adam_eps: float = 1e-15      # 3DGS value; tiny so small grads still move


@dataclasses.dataclass(frozen=True)
class DensifyConfig:
  """Adaptive density control (3DGS defaults); steps count finished steps."""
  start: int = 500             # first densification after this many steps
  stop: int = 15_000           # densify/prune/reset only while step < stop
  every: int = 100             # densification cadence in steps
  grad_threshold: float = 2e-4  # mean |d loss / d NDC xy| over visible views
  percent_dense: float = 0.01  # x extent: clone at or below, split above
  split_scale: float = 1.6     # a split child has scale / this (2 children)
  min_opacity: float = 0.005   # prune below this opacity
  max_world_size: float = 0.1  # x extent: prune larger (after first reset)
  max_screen_size: float = 20.0  # pixels: prune larger radius (after reset)
  opacity_reset_every: int = 3000  # 0 = never; opacity -> min(op, reset_to)
  opacity_reset_to: float = 0.01  # opacity after a reset
  sh_degree_every: int = 1000  # raise the active SH degree this often


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """The training loop."""
  steps: int = 30_000          # optimisation steps (3DGS: 30k)
  batch_size: int = 1          # B views per step, loss = their mean; B > 1
  #   spreads them over every device (B a multiple of the device count)
  seed: int = 0                # PRNG seed (views, backgrounds, splits)
  lambda_dssim: float = 0.2    # loss = (1 - l) L1 + l (1 - SSIM)
  random_background: bool = False  # a random colour behind splats per step
  background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # else this RGB
  log_every: int = 100         # host fetches metrics, checks finiteness
  eval_every: int = 1000       # test PSNR for the curve; 0 = only at the end
  checkpoint_every: int = 5000  # 0 = only at the end


# The paper's prompt sets: distractors D and static scene S (eqs. 5-7).
PAPER_DISTRACTOR_PROMPTS = ("a photo of a person", "a photo of people",
                            "a photo of pedestrians", "a photo of hands",
                            "a photo of a balloon")
PAPER_STATIC_PROMPTS = ("a photo of a building", "a photo of a wall",
                        "a photo of furniture")
# The paper's run length; `SemanticConfig.scaled_to` scales its schedule.
PAPER_STEPS = 20_000
# "uniform" is a control for localized evidence (benchmarks only): every
# pixel of every training view gets the ground-truth masks' mean transient
# fraction, i.e. the same total evidence as ORACLE-PIXEL with no location.
# "residual" needs nothing but the photos (the step's own residual);
# "oracle_patch" is the ground-truth mask at dense CLIP's patch resolution
# (benchmarks only: what a perfect dense CLIP would give).
SCORERS = ("off", "clip", "oracle", "uniform", "residual", "oracle_patch")
WEIGHTINGS = ("visibility", "contribution")
# Where a scorer's evidence comes from: "image", the paper's one score per
# rendered view; "pixel", a per-pixel transient probability map per training
# view, accumulated into each Gaussian by its blending weights.
EVIDENCES = ("image", "pixel")


@dataclasses.dataclass(frozen=True)
class SemanticConfig:
  """The CLIP-GS semantic stage (paper defaults, eqs. 5-13).

  Steps count finished steps, as in DensifyConfig. The step that starts at
  `step` scores its view when step >= accumulate_start and
  (step - accumulate_start) % score_every == 0, adds the opacity loss when
  step >= reg_start, and after `step` finished steps the host loop prunes
  when step >= prune_start and (step - prune_start) % prune_every == 0.
  """
  scorer: str = "off"          # off | clip | oracle | uniform (oracle,
  #   uniform: benchmarks only, read the ground-truth masks)
  evidence: str = "image"      # image (the paper) | pixel (localized maps)
  distractor_prompts: tuple[str, ...] = PAPER_DISTRACTOR_PROMPTS  # D
  static_prompts: tuple[str, ...] = PAPER_STATIC_PROMPTS  # S, logged only
  beta: float = 0.1            # accumulation rate (eq. 8)
  lambda_c: float = 0.01       # CLIP opacity loss weight (eq. 11; 0: off)
  prune: bool = True           # eq. 13 pruning (False: an ablation)
  tau: float = 0.015           # prune when s_j > tau (eq. 13), image evidence
  tau_p: float = 0.5           # pixel evidence: prune when the probability
  #   s_j that a Gaussian's light is transient exceeds this (every scene)
  n_min: float = 10.0          # ... or n_j < n_min and alpha_j < alpha_min;
  alpha_min: float = 0.1       #     n_min is divided by score_every
  accumulate_start: int = 500  # first scored step
  reg_start: int = 2000        # first step with the opacity loss
  prune_start: int = 5000      # first prune after this many steps
  prune_every: int = 1000      # prune cadence
  score_every: int = 1         # score every k-th step (paper: 1)
  weighting: str = "visibility"  # paper: a visible Gaussian gains the view's
  #   score once; "contribution": weighted by its blending-weight sum in the
  #   view (n_j still counts views; see semantic.accumulate)
  clip_variant: str = "ViT-B/32"  # frozen tower; 224x224 resized input
  oracle_saturation: float = 0.1  # transient area fraction that scores 1.0
  agreement: bool = True       # pixel evidence: a transient pixel counts
  #   as far as the render reproduces the photo (semantic.agreement; a
  #   second forward pass on scored steps), the rest of it not at all;
  #   False: the raw map, in the render's own pass
  loss_masking: bool = False   # pixel evidence: weight the photometric loss
  #   per pixel by 1 - m (robust-3DGS style); off in the paper
  reset_quiet: int = 0         # steps after each opacity reset without
  #   the opacity loss or eq. 13 prune (0: the paper). Adam's opacity
  #   moments are zeroed at a reset, so until a row's photometric gradient
  #   reaches them the small, steady loss gradient moves its logit at
  #   several times the learning rate, under min_opacity (BUILD_NOTES.md,
  #   "Localized evidence")
  max_prune_fraction: float = 0.5  # a prune event that would remove more
  #   of the alive Gaussians than this removes none (1.0: the paper, no guard)
  dense_input_size: int = 448  # clip + pixel: CLIP input side, a multiple
  #   of the patch size (B/32: a 14x14 patch grid)
  # The residual map (scorer "residual"; clipgs_jax/residual.py): a pixel
  # is transient where the step's own render misses the photo by more than
  # a running quantile of the residuals.
  residual: bool = False       # pixel evidence with a semantic map (clip,
  #   oracle_patch): keep the residual test only where the semantic map's
  #   p(transient) > 0.5 (implied by scorer "residual", which has none)
  residual_rule: str = "sls"   # sls (SpotLessSplats) | robustnerf
  residual_quantile: float = 0.7  # inlier share (SLS 0.7; RobustNeRF 0.8)
  residual_decay: float = 0.95  # histogram decay per step (RobustNeRF: 0)
  residual_warmup: float = 3e-3  # rate of the Bernoulli warm-up; 0: none
  residual_median_factor: float = 3.0  # threshold >= this x the median
  #   residual (0: the quantile alone; BUILD_NOTES.md, "Transient masks
  #   without an oracle": a quantile masks its share of a clean view too)
  residual_min_threshold: float = 0.0  # threshold >= this mean absolute
  #   colour error (0: none)
  features: str = ""           # residual map: "" per pixel, or "alex" /
  #   "vgg": each photo's ImageNet-feature regions (features.py) take the
  #   majority verdict of the residual test inside them

  @property
  def enabled(self) -> bool:
    """Guidance runs: a scorer is chosen (config.check rejects a CLIP
    scorer without distractor prompts instead of running vanilla)."""
    return self.scorer != "off"

  @property
  def uses_residual(self) -> bool:
    """The step computes the residual map (and carries its statistics)."""
    return self.enabled and (self.scorer == "residual" or self.residual)

  @property
  def localized(self) -> bool:
    """Evidence is a per-pixel map (s_j is a probability, tau_p applies)."""
    return self.enabled and self.evidence == "pixel"

  def scaled_to(self, steps: int) -> "SemanticConfig":
    """The schedule scaled from the paper's 20k steps to `steps`."""
    f = steps / PAPER_STEPS
    scale = lambda x: max(1, round(x * f))
    return dataclasses.replace(
        self, accumulate_start=scale(self.accumulate_start),
        reg_start=scale(self.reg_start), prune_start=scale(self.prune_start),
        prune_every=scale(self.prune_every))


@dataclasses.dataclass(frozen=True)
class DataConfig:
  """Which scene a run reads, and how."""
  scene: str | None = None     # folder or .npz pack; None = embedded scene
  downscale: int = 1           # image downscale factor (1: full size)
  train_split: str = "clutter"  # RobustNeRF: clutter views or clean twins


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """How a finished run is measured."""
  lpips_net: str = "alex"      # LPIPS backbone of the test metrics
  curve_points: int = 20       # test-PSNR points along the run (curve.json);
  #   sets train.eval_every = steps // curve_points (0: keep eval_every)


@dataclasses.dataclass(frozen=True)
class Config:
  """Everything a run needs; `scene_extent` is filled in from the scene."""
  gaussians: GaussiansConfig = GaussiansConfig()  # capacity, initialisation
  optim: OptimConfig = OptimConfig()      # learning rates
  densify: DensifyConfig = DensifyConfig()  # adaptive density control
  train: TrainConfig = TrainConfig()      # loop, loss, logging
  render: RenderConfig = RenderConfig()   # rasterizer settings
  semantic: SemanticConfig = SemanticConfig()  # CLIP-GS guidance (off)
  data: DataConfig = DataConfig()         # scene, downscale, split
  eval: EvalConfig = EvalConfig()         # test metrics, curve
  scene_extent: float = 0.0    # camera-centre radius x 1.1; 0 = from scene


class _HostOnly:
  """Stands in for a config field that compiled code must not read.

  Arithmetic, attribute access and truth tests on it raise, so a traced
  function that starts reading such a field fails at trace time instead of
  silently using one run's value for all the runs that share its program.
  """

  def __bool__(self):
    raise TypeError("a host-only config field was read by compiled code; "
                    "remove it from config.compiled_part's dropped fields")

  def __repr__(self):
    return "HOST_ONLY"


HOST_ONLY = _HostOnly()
# Fields that only the host loop reads: when to log, evaluate and checkpoint,
# the seed (it makes the initial PRNG key, which the state carries), the
# scene and split, and the test metrics.
_HOST_TRAIN_FIELDS = ("seed", "log_every", "eval_every", "checkpoint_every")
# SemanticConfig fields that the train step does not read: the prune rule
# (its own jitted function, guidance.prune), and what builds the scorer
# (guidance.make_scorer), which the step gets as an argument.
SEMANTIC_FIELDS_NOT_IN_STEP = (
    "prune", "tau", "tau_p", "n_min", "alpha_min", "prune_start",
    "prune_every", "max_prune_fraction", "static_prompts", "clip_variant",
    "dense_input_size", "oracle_saturation")


def compiled_part(cfg: Config, semantic_dropped: tuple[str, ...] = ()
                  ) -> Config:
  """`cfg` with the fields its compiled functions do not read as HOST_ONLY.

  Dropped: data, eval, the host fields of train, and the `semantic_dropped`
  fields of semantic. The jitted step, densify and prune functions are
  cached by this (`cache_by_compiled_part`), so runs that differ only there
  (a table's vanilla and clean rows; two runs that differ in tau) share one
  compiled program instead of compiling the same program again.
  """
  return dataclasses.replace(
      cfg, data=HOST_ONLY, eval=HOST_ONLY,
      train=dataclasses.replace(
          cfg.train, **dict.fromkeys(_HOST_TRAIN_FIELDS, HOST_ONLY)),
      semantic=dataclasses.replace(
          cfg.semantic, **dict.fromkeys(semantic_dropped, HOST_ONLY)))


def cache_by_compiled_part(semantic_dropped: tuple[str, ...] = ()):
  """Decorator factory: caches `make(cfg)` by `compiled_part(cfg, ...)`.

  `make` receives the compiled part; `.cache_clear()` works as for
  functools.lru_cache.
  """
  def decorate(make):
    cached = functools.lru_cache(maxsize=None)(make)

    @functools.wraps(make)
    def wrapper(cfg: Config):
      return cached(compiled_part(cfg, semantic_dropped))

    wrapper.cache_clear = cached.cache_clear
    return wrapper
  return decorate


def to_dict(cfg: Config) -> dict:
  """JSON-ready nested dict of a config."""
  return dataclasses.asdict(cfg)


def from_dict(d: dict) -> Config:
  """Inverse of `to_dict`; unknown keys raise (no silent typos)."""
  return _build(Config, d, "")


# The checkout's config files (configs/ next to the package), found when
# the package is imported from the checkout (python -m pytest, PYTHONPATH)
# or installed editable; scripts pass config files by path.
CONFIGS_DIR = os.path.join(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__))), "configs")
# ConfigDict keys that the builder consumes instead of storing:
# semantic.scale_schedule scales the paper's semantic schedule to
# train.steps (SemanticConfig.scaled_to), for short runs.
SCALE_SCHEDULE = "scale_schedule"


def _field_value(default, value, key: str):
  """`value` in the type of the field whose default is `default`."""
  if isinstance(default, tuple):
    if isinstance(value, str):
      # "a,b" in a config file or dict; "" is ().
      value = [v for v in value.split(",") if v]
    return tuple(value)
  if isinstance(default, bool) or default is None:
    return value
  if isinstance(default, float) and isinstance(value, int):
    return float(value)
  if not isinstance(value, type(default)):
    raise ValueError(f"config: {key}={value!r} must be of type "
                     f"{type(default).__name__} (the default is {default!r}).")
  return value


def _optional_str(cls, name: str) -> bool:
  hint = typing.get_type_hints(cls)[name]
  return isinstance(hint, types.UnionType) and str in hint.__args__


def _build(cls, values, prefix: str):
  """cls(**values) with nested dataclasses; unknown keys raise, by name."""
  fields = {f.name for f in dataclasses.fields(cls)}
  unknown = sorted(set(values) - fields)
  if unknown:
    raise ValueError(f"config: unknown key {prefix}{unknown[0]} (a "
                     f"{cls.__name__} has {', '.join(sorted(fields))}).")
  kwargs = {}
  for name, value in values.items():
    default = getattr(cls(), name)
    key = prefix + name
    if dataclasses.is_dataclass(default):
      if not isinstance(value, dict):
        raise ValueError(f"config: {key} must be a section, got {value!r}.")
      value = _build(type(default), value, key + ".")
    elif value is None and not _optional_str(cls, name):
      raise ValueError(f"config: {key} is not set; give it a value.")
    elif value is not None:
      value = _field_value(default, value, key)
    kwargs[name] = value
  return cls(**kwargs)


def from_config_dict(cd: ml_collections.ConfigDict, *,
                     auto_steps: int = TrainConfig.steps) -> Config:
  """The frozen Config that a config file (ConfigDict) describes, unchecked.

  Every key must be a Config field of the field's type (unknown keys and
  wrong types raise ValueError, named), except semantic.scale_schedule
  (see SCALE_SCHEDULE). train.steps None means `auto_steps`;
  eval.curve_points > 0 sets train.eval_every. The values are checked by
  `check`, which calls this.

  Args:
    cd: the ConfigDict (configs/*.py get_config(), with overrides).
    auto_steps: int, the steps of a config whose train.steps is None.
  Returns:
    Config.
  """
  values = cd.to_dict() if isinstance(cd, ml_collections.ConfigDict) else (
      dict(cd))
  sem = dict(values.get("semantic", {}))
  scale = bool(sem.pop(SCALE_SCHEDULE, False))
  train = dict(values.get("train", {}))
  if train.get("steps", 0) is None:
    train["steps"] = auto_steps
  cfg = _build(Config, dict(values, semantic=sem, train=train), "")
  t = cfg.train
  if cfg.eval.curve_points > 0:
    t = dataclasses.replace(
        t, eval_every=max(1, t.steps // cfg.eval.curve_points))
  sem = cfg.semantic.scaled_to(t.steps) if scale else cfg.semantic
  return dataclasses.replace(cfg, train=t, semantic=sem)


def _positive(ok: bool, key: str, value, fix: str) -> None:
  if not ok:
    raise app.UsageError(f"--config.{key}={value} {fix}")


def _semantic_problems(sem: SemanticConfig) -> list[str]:
  """What makes a SemanticConfig unable to run, one phrase per field."""
  problems = []
  if sem.scorer not in SCORERS:
    problems.append(f"scorer={sem.scorer!r} is not one of "
                    f"{', '.join(SCORERS)}")
  if sem.evidence not in EVIDENCES:
    problems.append(f"evidence={sem.evidence!r} is not one of "
                    f"{', '.join(EVIDENCES)}")
  if sem.scorer == "clip" and not sem.distractor_prompts:
    problems.append("scorer='clip' has no distractor prompts; give some "
                    "(e.g. the paper's) or use scorer='off' for vanilla 3DGS")
  if (sem.scorer == "clip" and sem.evidence == "pixel"
      and not sem.static_prompts):
    problems.append("scorer='clip' with evidence='pixel' needs static "
                    "prompts: p(distractor) is a softmax over D and S, which "
                    "is identically 1 without S")
  if not 0.0 <= sem.tau_p <= 1.0:
    problems.append(f"tau_p={sem.tau_p} is not in [0, 1]")
  if not 0.0 < sem.max_prune_fraction <= 1.0:
    problems.append(f"max_prune_fraction={sem.max_prune_fraction} is not in "
                    "(0, 1] (1.0 lifts the guard)")
  if sem.scorer == "uniform" and sem.evidence != "pixel":
    problems.append("scorer='uniform' is a per-pixel control map; it needs "
                    "evidence='pixel'")
  problems += _residual_problems(sem)
  if sem.loss_masking and sem.evidence != "pixel":
    problems.append("loss_masking needs evidence='pixel' (a per-pixel map)")
  if sem.dense_input_size <= 0:
    problems.append(f"dense_input_size={sem.dense_input_size} must be a "
                    "positive multiple of the ViT's patch size")
  if sem.weighting not in WEIGHTINGS:
    problems.append(f"weighting={sem.weighting!r} is not one of "
                    f"{', '.join(WEIGHTINGS)}")
  if not 0.0 <= sem.tau <= 1.0:
    problems.append(f"tau={sem.tau} is not in [0, 1]")
  if not sem.beta > 0:
    problems.append(f"beta={sem.beta} must be positive")
  if not sem.lambda_c >= 0:
    problems.append(f"lambda_c={sem.lambda_c} must be >= 0")
  if (sem.enabled and sem.lambda_c == 0 and not sem.prune
      and not sem.loss_masking):
    problems.append("lambda_c=0 with prune and loss_masking off leaves "
                    "guidance nothing to do; use scorer='off' for vanilla "
                    "3DGS")
  for name in ("accumulate_start", "reg_start", "prune_start",
               "reset_quiet"):
    if getattr(sem, name) < 0:
      problems.append(f"{name}={getattr(sem, name)} must be >= 0")
  for name in ("prune_every", "score_every"):
    if getattr(sem, name) < 1:
      problems.append(f"{name}={getattr(sem, name)} must be >= 1")
  if not 0.0 < sem.oracle_saturation <= 1.0:
    problems.append(f"oracle_saturation={sem.oracle_saturation} is not in "
                    "(0, 1]")
  if any(not p.strip() for p in sem.distractor_prompts + sem.static_prompts):
    problems.append("a prompt is empty")
  return problems


def _residual_problems(sem: SemanticConfig) -> list[str]:
  """What makes the residual map's settings unable to run."""
  problems = []
  if sem.scorer in ("residual", "oracle_patch") and sem.evidence != "pixel":
    problems.append(f"scorer={sem.scorer!r} is a per-pixel map; it needs "
                    "evidence='pixel'")
  if sem.residual and (sem.scorer not in ("clip", "oracle_patch")
                       or sem.evidence != "pixel"):
    problems.append("residual=True combines the residual map with a "
                    "semantic map: it needs scorer='clip' or 'oracle_patch' "
                    "and evidence='pixel' (scorer='residual' is the residual "
                    "map alone)")
  if sem.features and sem.features not in features.NETS:
    problems.append(f"features={sem.features!r} is not one of "
                    f"{', '.join(sorted(features.NETS))} (or '' for none)")
  if sem.features and not sem.uses_residual:
    problems.append("features votes the residual test over regions: it "
                    "needs scorer='residual' or residual=True")
  if sem.residual_rule not in residual.RULES:
    problems.append(f"residual_rule={sem.residual_rule!r} is not one of "
                    f"{', '.join(residual.RULES)}")
  if not 0.0 < sem.residual_quantile < 1.0:
    problems.append(f"residual_quantile={sem.residual_quantile} is not in "
                    "(0, 1)")
  if not 0.0 <= sem.residual_decay < 1.0:
    problems.append(f"residual_decay={sem.residual_decay} is not in [0, 1)")
  if not sem.residual_median_factor >= 0:
    problems.append(f"residual_median_factor={sem.residual_median_factor} "
                    "must be >= 0")
  if not 0.0 <= sem.residual_min_threshold < 1.0:
    problems.append(f"residual_min_threshold={sem.residual_min_threshold} "
                    "is not in [0, 1)")
  if not sem.residual_warmup >= 0:
    problems.append(f"residual_warmup={sem.residual_warmup} must be >= 0")
  return problems


def check(values: dict | ml_collections.ConfigDict) -> Config:
  """The checked Config of one run: every config check, in one place.

  Runs before any scene or weights are read (only the scene's existence
  is): keys and types (`from_config_dict`), then every value. train.steps
  None means default_scene.TRAIN_STEPS on the embedded scene (data.scene
  None) and TrainConfig's 30k on a scene folder. data.scene becomes an
  absolute path, so that --resume from another folder matches.

  Args:
    values: a config file's ConfigDict (with overrides), or its dict.
  Returns:
    Config.
  Raises:
    app.UsageError: a bad key or value; the line names it as
      --config.SECTION.FIELD and says the fix.
    FileNotFoundError: data.scene is neither a folder nor a pack file.
  """
  if isinstance(values, ml_collections.ConfigDict):
    values = values.to_dict()
  embedded = (values.get("data") or {}).get("scene") is None
  auto = default_scene.TRAIN_STEPS if embedded else TrainConfig.steps
  try:
    cfg = from_config_dict(values, auto_steps=auto)
  except ValueError as e:
    raise app.UsageError(str(e)) from e
  t = cfg.train
  _positive(t.steps > 0, "train.steps", t.steps, "must be positive")
  _positive(t.batch_size >= 1, "train.batch_size", t.batch_size,
            "must be positive (1: one view per step)")
  _positive(t.checkpoint_every >= 0, "train.checkpoint_every",
            t.checkpoint_every, "must be >= 0 (0: only at the end)")
  _positive(cfg.render.tile_budget > 0, "render.tile_budget",
            cfg.render.tile_budget, "must be positive; raise it when the "
            "log warns that tile-list entries were dropped")
  _positive(cfg.data.downscale >= 1, "data.downscale", cfg.data.downscale,
            "must be a positive integer (1: full size)")
  _positive(cfg.eval.curve_points >= 0, "eval.curve_points",
            cfg.eval.curve_points, "must be >= 0 (0: keep train.eval_every)")
  problems = _semantic_problems(cfg.semantic)
  if problems:
    raise app.UsageError("--config.semantic: SemanticConfig: "
                         + "; ".join(problems) + ".")
  data, ev = cfg.data, cfg.eval
  cli.require(data.train_split in scene_lib.TRAIN_SPLITS,
              "config.data.train_split", data.train_split,
              f"is not one of {', '.join(scene_lib.TRAIN_SPLITS)}")
  nets = metrics_lib.LPIPS_NETS
  cli.require(ev.lpips_net in nets, "config.eval.lpips_net", ev.lpips_net,
              f"is not one of {', '.join(nets)}")
  if data.scene is None:
    return cfg
  if data.scene.endswith(scene_lib.PACK_SUFFIX):
    cli.require_file("scene", data.scene)
  else:
    cli.require_folder("scene", data.scene)
  return dataclasses.replace(cfg, data=dataclasses.replace(
      data, scene=os.path.abspath(data.scene)))


def to_config_dict(cfg: Config) -> ml_collections.ConfigDict:
  """A ConfigDict of `cfg` with every field, for config files to edit.

  data.scene is a string placeholder (None: the embedded scene), so that a
  command line can set it; semantic.scale_schedule starts False.
  """
  cd = ml_collections.ConfigDict(to_dict(cfg))
  cd.data.scene = ml_collections.config_dict.placeholder(str)
  if cfg.data.scene is not None:
    cd.data.scene = cfg.data.scene
  cd.semantic[SCALE_SCHEDULE] = False
  return cd


def load_file(path: str) -> ml_collections.ConfigDict:
  """get_config() of the config file at `path` (as --config=path loads it).

  Raises:
    FileNotFoundError: no such file.
    ValueError: the file has no get_config().
  """
  path = os.fspath(path)
  if not os.path.isfile(path):
    raise FileNotFoundError(f"config file {path} does not exist; pass a "
                            f"file such as {CONFIGS_DIR}/default.py")
  name = "clipgs_config_" + os.path.splitext(os.path.basename(path))[0]
  spec = importlib.util.spec_from_file_location(name, path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  if not hasattr(module, "get_config"):
    raise ValueError(f"config file {path} defines no get_config(); add one "
                     "that returns an ml_collections.ConfigDict")
  return module.get_config()


def named(name: str) -> Config:
  """The Config of the checkout's configs/<name>.py, e.g. named("smoke")
  (one run's config; a config with train.steps None gets 30k steps)."""
  return from_config_dict(load_file(os.path.join(CONFIGS_DIR, name + ".py")))
