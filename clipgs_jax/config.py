"""Frozen configuration dataclasses with the paper's and 3DGS's defaults,
and the compiled part of a config that keys the jit caches.

Config files become a checked Config in config_file.py (`check`).
"""

import dataclasses
import functools


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
  rare_needs_evidence: bool = False  # the n_min clause prunes only rows
  #   with s_j > 0: some of their light fell on pixels the map calls
  #   transient (False: the paper). Pixel evidence scores every view, and
  #   rows a densification just made, or that few views see, sit under
  #   n_min: on bonsai they are mostly scene; not yet the default
  #   (BUILD_NOTES.md, "Tried, reverted")
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
  prune_harm: float = 0.0      # a row of eq. 13's semantic clause is kept
  #   when this share of its blending weight over the training views falls
  #   on pixels that removing the clause's rows makes worse (two renders of
  #   the training views that see them, each prune event;
  #   render_without.py). 0: off; it spares part of bonsai's window, not
  #   all (BUILD_NOTES.md, "Which rows eq. 13 takes")
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
  residual_warmup: float = 3e-3  # rate of the Bernoulli warm-up per step
  #   of a 20k-step run (SLS's 3e-3); scaled_to divides it by the run's
  #   share of 20k, so the warm-up ends at the same share of any run
  #   (0.024 at 2,500 steps); 0: none
  residual_start: int = 0      # the training step uses no residual map
  #   (no pixel masked, no evidence) before this step, scaled like
  #   accumulate_start. Masking what the smeared early render misses keeps
  #   static scene unfit (bonsai), and starting late lets transients be
  #   fit (bird independent): BUILD_NOTES.md, "Transient masks without an
  #   oracle". Mask quality reports the test's map at every step
  residual_median_factor: float = 3.0  # threshold >= this x the median
  #   residual (0: the quantile alone; BUILD_NOTES.md, "Transient masks
  #   without an oracle": a quantile masks its share of a clean view too)
  residual_min_threshold: float = 0.15  # threshold >= this mean absolute
  #   colour error (0: none). Relative floors stay at the fit's own error
  #   level, so a clean view stays masked where the fit lags; an absolute
  #   one lets a clean view's map shrink as the fit improves (BUILD_NOTES)
  residual_min_alpha: float = 0.9  # a pixel is transient only where the
  #   render's alpha exceeds this (0: everywhere; with features: only in a
  #   region where most pixels' alpha does). A transient hides a
  #   surface other views reconstruct; where the model has none, a high
  #   residual is static scene not yet fit, and masking it keeps it unfit
  #   (BUILD_NOTES.md, "Transient masks without an oracle")
  residual_min_share: float = 0.03  # a view whose map, after the gates,
  #   marks less than this share of its pixels is taken as clean: no
  #   transient pixel, every pixel in the loss (0: off). A fit error
  #   marks a few regions of a view (bonsai's clean twin: up to 2.1 %),
  #   a transient the benchmarks paste 5-42 % of one; a smaller one goes
  #   unmasked (BUILD_NOTES.md, "The share floor")
  features: str = ""           # residual map: "" per pixel, or "alex" /
  #   "vgg": each photo's ImageNet-feature regions (features.py) take the
  #   majority verdict of the residual test inside them
  residual_vote: float = 0.5   # features: a region is transient when at
  #   least this share of its pixels fail the residual test (SLS-agg: 0.5)
  residual_uniformity: float = 0.35  # features: before
  #   residual_uniform_until, a region the vote calls transient is masked
  #   only where the residual's std / mean over its pixels is below this
  #   (0: no such gate). The early, smeared render misses static regions
  #   at their edges and a transient throughout (BUILD_NOTES.md,
  #   "Transient masks without an oracle")
  residual_uniform_until: int = 10_000  # paper steps, scaled like
  #   residual_start (1,250 of 2,500)

  @property
  def enabled(self) -> bool:
    """Guidance runs: a scorer is chosen (config_file.check rejects a CLIP
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
        residual_start=(scale(self.residual_start) if self.residual_start
                        else 0),
        residual_uniform_until=scale(self.residual_uniform_until),
        prune_every=scale(self.prune_every),
        residual_warmup=self.residual_warmup / f)


@dataclasses.dataclass(frozen=True)
class DataConfig:
  """Which scene a run reads, and how."""
  scene: str | None = None     # folder or .npz pack; None = embedded scene
  downscale: int = 1           # image downscale factor (1: full size)
  train_split: str = "clutter"  # RobustNeRF: clutter views or clean twins
  background: str = "white"    # behind photos with alpha: white or black


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
    "prune", "tau", "tau_p", "n_min", "alpha_min", "rare_needs_evidence",
    "prune_harm",
    "prune_start", "prune_every", "max_prune_fraction", "static_prompts",
    "clip_variant", "dense_input_size", "oracle_saturation")


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
