"""A run's settings: frozen dataclasses with the paper's and 3DGS's
defaults, one section for each stage that reads it, each with the checks of
its fields (`check`).

Config files and command lines become a Config in config_file.py, which
calls `check` before any scene or weights are read; compiled.py says which
fields compiled code reads.
"""

import dataclasses

from absl import app

from clipgs_jax import guidance_config
from clipgs_jax import metrics


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
  # guidance_config.py: CLIP-GS (off), per-pixel evidence, the two maps
  semantic: guidance_config.SemanticConfig = guidance_config.SemanticConfig()
  pixel: guidance_config.PixelConfig = guidance_config.PixelConfig()
  residual: guidance_config.ResidualConfig = guidance_config.ResidualConfig()
  learned: guidance_config.LearnedConfig = guidance_config.LearnedConfig()
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
  def uses_memory(self) -> bool:
    """The residual map keeps each view's marked pixels in the state."""
    return self.uses_residual and self.residual.remember

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
