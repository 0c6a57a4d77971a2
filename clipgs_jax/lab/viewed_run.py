"""A finished run as the viewer shows it: splats, s_j, the prune preview and
each view's photo, render, transient map and mask (host numpy, no GUI)."""

import dataclasses
import functools
import os
from typing import Any

import jax
import jax.numpy as jnp
from matplotlib import colormaps
import numpy as np

from clipgs_jax import camera as camera_lib
from clipgs_jax import checkpoint
from clipgs_jax import config as config_lib
from clipgs_jax import evaluation
from clipgs_jax import gaussians
from clipgs_jax import guidance
from clipgs_jax import ply
from clipgs_jax import run as run_lib
from clipgs_jax import semantic
from clipgs_jax import sh
from clipgs_jax import state as state_lib
from clipgs_jax import train
from clipgs_jax.data import default_scene
from clipgs_jax.maps import learned
from clipgs_jax.maps import residual

SPLITS = ("train", "test")
SCORE_COLORMAP = "viridis"     # s_j, low to high; no red in it, so the
HIGHLIGHT_RGB = (1.0, 0.1, 0.1)  # rows a prune would remove stand out


@dataclasses.dataclass(frozen=True)
class Splats:
  """Gaussians as a splat renderer takes them.

  Attributes:
    centers: float32 [N, 3], world positions.
    covariances: float32 [N, 3, 3], R diag(scale^2) R^T.
    rgbs: float32 [N, 3] in [0, 1], the SH DC colour.
    opacities: float32 [N, 1] in [0, 1].
  """
  centers: np.ndarray
  covariances: np.ndarray
  rgbs: np.ndarray
  opacities: np.ndarray


# One compiled program, not one per operation: op by op, the 40-odd
# operations took 3 s of compiles at startup on the 2-core box.
@jax.jit
def _splat_arrays(params: gaussians.GaussianParams):
  act = gaussians.activate(params)
  rot = act.rotations                                       # [N, 3, 3]
  cov = jnp.einsum("nij,nj,nkj->nik", rot, jnp.square(act.scales), rot)
  rgb = sh.to_color(params.sh_dc, params.sh_rest,
                    jnp.zeros_like(params.means), 0)        # DC term only
  return act.means, cov, jnp.clip(rgb, 0.0, 1.0), act.opacities[:, None]


def to_splats(params: gaussians.GaussianParams) -> Splats:
  """The splats of every row of `params` (through gaussians.activate)."""
  return Splats(*(np.asarray(x, np.float32)
                  for x in _splat_arrays(params)))


@dataclasses.dataclass(frozen=True)
class ViewedRun:
  """One run folder's Gaussians and what guidance knew about them.

  Attributes:
    path: str, the run folder.
    info: run.json (scene, downscale, guidance label, ...).
    cfg: the resolved config.Config of the run.
    params: GaussianParams (numpy) of the N alive rows.
    stats: state.SemanticStats (numpy, [N]) from the checkpoint of a
      guided run, else None (vanilla, or a run with only its PLY).
    maps: the residual map's statistics (residual.ResidualState, numpy)
      from the checkpoint of a run that used it, else None.
    degree: int, the SH degree the run's last steps used (all bands for
      a run with only its PLY).
    splats: Splats of `params`.
    pruned: Splats of the rows the run's semantic prunes removed
      (pruned.ply), or None where the folder has none.
  """
  path: str
  info: dict[str, Any]
  cfg: config_lib.Config
  params: gaussians.GaussianParams
  stats: state_lib.SemanticStats | None
  maps: residual.ResidualState | None
  degree: int
  splats: Splats
  pruned: Splats | None

  @property
  def name(self) -> str:
    return os.path.basename(os.path.normpath(self.path))

  @property
  def scores(self) -> np.ndarray | None:
    """float32 [N] s_j (semantic.normalized_scores), or None."""
    if self.stats is None:
      return None
    return np.asarray(semantic.normalized_scores(self.stats), np.float32)


def read_info(path: str) -> dict[str, Any]:
  """A run folder's run.json, read without its Gaussians or scene.

  Raises:
    FileNotFoundError, ValueError: one line naming the folder and the fix.
  """
  if not os.path.isdir(path):
    raise FileNotFoundError(f"run folder {path} does not exist; pass a "
                            "folder written by experiments/train.py")
  missing = [n for n in (run_lib.RUN_JSON, run_lib.CONFIG_JSON)
             if not os.path.isfile(os.path.join(path, n))]
  if missing:
    raise ValueError(f"{path} is not a run folder (no {', '.join(missing)})"
                     "; pass a folder written by experiments/train.py")
  return run_lib.read_json(os.path.join(path, run_lib.RUN_JSON),
                           "scene and downscale")


def load(path: str) -> ViewedRun:
  """Reads a run folder: its checkpoint (or else its PLY) and pruned.ply.

  Raises:
    FileNotFoundError, ValueError: one line naming the folder and the fix.
  """
  info = read_info(path)
  cfg = run_lib.load_config(path)
  ckpt = os.path.join(path, train.CHECKPOINT_NAME)
  ply_path = os.path.join(path, run_lib.POINT_CLOUD_PLY)
  stats, maps = None, None
  if os.path.isfile(ckpt):
    arrays = checkpoint.read_arrays(ckpt, *(
        checkpoint.STATE_PREFIX + n for n in ("params/", "semantic/",
                                              "maps/", "alive", "step")))
    field = lambda group, n: arrays[f"{checkpoint.STATE_PREFIX}{group}{n}"]
    alive = field("alive", "")
    params = gaussians.GaussianParams(**{
        f.name: field("params/", f.name)[alive]
        for f in dataclasses.fields(gaussians.GaussianParams)})
    if cfg.semantic.enabled:
      stats = state_lib.SemanticStats(**{
          f.name: field("semantic/", f.name)[alive]
          for f in dataclasses.fields(state_lib.SemanticStats)})
    if cfg.uses_residual:
      # The learned map's classifier: its weights (no Adam state).
      prefix = f"{checkpoint.STATE_PREFIX}maps/classifier/params/"
      weights = {k[len(prefix):]: v for k, v in arrays.items()
                 if k.startswith(prefix)}
      maps = residual.ResidualState(
          histogram=field("maps/", "histogram"),
          threshold=field("maps/", "threshold"),
          classifier=(learned.Classifier(params=weights, opt_state=None)
                      if weights else None),
          memory=arrays.get(f"{checkpoint.STATE_PREFIX}maps/memory"))
    degree = int(sh.active_degree(int(field("step", "")),
                                  cfg.densify.sh_degree_every,
                                  cfg.gaussians.sh_degree))
  elif os.path.isfile(ply_path):
    params = jax.tree.map(np.asarray, ply.read_ply(ply_path)[0])
    degree = params.sh_degree
  else:
    raise FileNotFoundError(
        f"run folder {path} has neither {train.CHECKPOINT_NAME} nor "
        f"{run_lib.POINT_CLOUD_PLY}; the run has not saved its Gaussians "
        "yet: resume it (experiments/train.py --resume) or pick another run")
  pruned_path = os.path.join(path, run_lib.PRUNED_PLY)
  pruned = (to_splats(ply.read_ply(pruned_path)[0])
            if os.path.isfile(pruned_path) else None)
  return ViewedRun(path=path, info=info, cfg=cfg, params=params,
                   stats=stats, maps=maps, degree=degree,
                   splats=to_splats(params), pruned=pruned)


def check_same_scene(a: str, b: str) -> None:
  """Raises ValueError unless run folders `a` (--run) and `b` (--compare)
  show the same scene and views; reads only their run.json."""
  def key(path):
    info = read_info(path)
    return (info.get("scene"), info.get("downscale"),
            info.get("train_split", "clutter"))
  if key(a) != key(b):
    raise ValueError(f"--compare={b} shows scene {key(b)}, --run={a} shows "
                     f"{key(a)} (scene, downscale, split); compare two runs "
                     "of the same scene")


def load_scene(run: ViewedRun):
  """The run's data.scene.Scene (cameras, photos, masks), from run.json."""
  if run.info.get("embedded_scene"):
    default_scene.ensure_default_scene()       # rebuilt if the cache went
  return run_lib.load_run(run.path)[2]


def score_range(run: ViewedRun) -> tuple[float, float]:
  """(low, high) of s_j: [0, 1] with pixel evidence, else [0, beta / 2]."""
  edges = guidance.histogram_edges(run.cfg.semantic)
  return edges[0], edges[-1]


def would_prune(run: ViewedRun, tau: float) -> dict[str, Any]:
  """What a semantic prune of the final model at threshold `tau` removes.

  Returns:
    {"by_score": bool [N], s_j > tau (with enough evidence), "faint":
    bool [N], the eq. 13 visibility rule, "refused": bool, the guard
    (semantic.guard_prune) would refuse the event and remove nothing}.
  """
  by_score, faint, refused = _would_prune(
      run.stats, run.params.opacity_logits, jnp.float32(tau),
      cfg=run.cfg)
  return {"by_score": np.asarray(by_score), "faint": np.asarray(faint),
          "refused": bool(refused)}


@functools.partial(jax.jit, static_argnames="cfg")
def _would_prune(stats, opacity_logits, tau, *, cfg):
  alive = jnp.ones(opacity_logits.shape, bool)
  by_score, faint = semantic.prune_masks(
      stats, opacity_logits, alive, **guidance.prune_thresholds(cfg, tau))
  _, _, refused = semantic.guard_prune(by_score, faint, alive,
                                       cfg.semantic.max_prune_fraction)
  return by_score, faint, refused


def colors(run: ViewedRun, by_score: bool, highlight=None) -> np.ndarray:
  """float32 [N, 3]: the splats' colours, or s_j through SCORE_COLORMAP,
  with the rows of bool [N] `highlight` in HIGHLIGHT_RGB."""
  rgb = run.splats.rgbs
  if by_score:
    low, high = score_range(run)
    unit = np.clip((run.scores - low) / (high - low), 0.0, 1.0)
    rgb = colormaps[SCORE_COLORMAP](unit)[:, :3].astype(np.float32)
  if highlight is not None:
    rgb = np.where(highlight[:, None], np.float32(HIGHLIGHT_RGB), rgb)
  return rgb


def views(scene, split: str):
  """The data.scene.Views of `split` ("train" or "test")."""
  return scene.train if split == "train" else scene.test


def camera(scene, split: str, index: int) -> camera_lib.Camera:
  return camera_lib.camera_at(views(scene, split).cameras, index)


def render(run: ViewedRun, scene, split: str, index: int,
           hidden=None) -> np.ndarray:
  """float32 [H, W, 3], our render of a view (CPU), without the rows of
  bool [N] `hidden` (a prune preview)."""
  one = _one_view(views(scene, split), index)
  n = run.params.means.shape[0]
  alive = np.ones(n, bool) if hidden is None else ~np.asarray(hidden)
  image = next(evaluation.renders(run.params, jnp.asarray(alive), one,
                                  run.cfg))[0]
  return np.asarray(image)


def ground_truth_mask(scene, split: str, index: int) -> np.ndarray | None:
  """bool [H, W], True = transient, where the scene has masks (training
  views of benchmarks), else None."""
  masks = views(scene, split).masks
  return None if masks is None else np.asarray(masks[index])


def transient_map(run: ViewedRun, scene, split: str, index: int
                  ) -> np.ndarray | None:
  """float32 [H, W] in [0, 1]: the per-pixel transient map a training step
  on this view would use with the run's final model (evaluation.view_map),
  or None where the run has none: vanilla, image-level evidence, test
  views, dense CLIP (it needs the CLIP weights), a residual map without
  its statistics (a run with only its PLY), masks the scene lacks.

  The map's source is built for this one view as guidance.make_scorer
  builds the run's (the residual test at the threshold the run ended with,
  the feature regions of this photo alone); UNIFORM's constant is the mean
  of every training mask, as guidance.uniform_control's.
  """
  sem = run.cfg.semantic
  masks = scene.train.masks
  needs_masks = sem.scorer in ("oracle", "uniform", "oracle_patch")
  if (split != "train" or not sem.localized or sem.scorer == "clip"
      or (needs_masks and masks is None)
      or (run.cfg.uses_residual and run.maps is None)):
    return None
  if sem.scorer == "uniform":
    return np.full(masks.shape[1:], np.mean(masks), np.float32)
  one = dataclasses.replace(scene, train=_one_view(scene.train, index))
  scorer = guidance.make_scorer(run.cfg, one)
  n = run.params.means.shape[0]
  return evaluation.view_map(run.params, np.ones(n, bool), run.maps, scorer,
                             one.train, 0, run.cfg,
                             np.int32(run.degree)).astype(np.float32)


def _one_view(vs, index: int):
  """data.scene.Views of view `index` of `vs` alone."""
  return dataclasses.replace(
      vs, cameras=jax.tree.map(lambda x: x[index:index + 1], vs.cameras),
      images=vs.images[index:index + 1], names=vs.names[index:index + 1],
      masks=None if vs.masks is None else vs.masks[index:index + 1])
