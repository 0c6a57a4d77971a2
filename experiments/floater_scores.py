"""Do the semantic scores single out transient floaters? A labelled probe.

  python experiments/floater_scores.py [--weighting=visibility|contribution]
      [--tau=1.0] [--n_min=10] [--score_every=1] [--steps=400]
      [--downscale=2] [--per_view=100]

On the embedded default scene, plants floaters where vanilla 3DGS puts the
Gaussians that explain a cluttered view's transient pixels: on the rays
through those pixels, just past the near plane, coloured from the view. The
SfM points of the static scene stay as they are, so every row is known to be
static or transient. Trains --steps steps without densification (rows keep
their identity) with the oracle scorer and the paper's schedule scaled to
--steps, then prints one JSON line: the quantiles of s_j over the surviving
static and floater rows, their median n_j, and the fraction of each pruned.
--tau=1.0 prunes nothing by score, to look at the raw distributions.
"""

import dataclasses
import json

from absl import flags
import jax
import numpy as np

from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax import guidance
from clipgs_jax import semantic
from clipgs_jax import train
from clipgs_jax.data import default_scene
from clipgs_jax.data import scene as scene_lib

# Floater depth in front of the camera that saw the transient (scene units):
# just past RenderConfig.near = 0.2.
FLOATER_DEPTH = (0.21, 0.3)


def plant_floaters(scene, rng: np.random.Generator, per_view: int):
  """(scene with floater points appended, number of floaters).

  Args:
    scene: a data.scene.Scene with training masks.
    rng: numpy Generator.
    per_view: floaters per cluttered training view (at most one per
      transient pixel).
  """
  cams = jax.device_get(scene.train.cameras)
  points, colors = [], []
  for k, mask in enumerate(scene.train.masks):
    rows, cols = np.nonzero(mask)
    if not len(rows):
      continue
    pick = rng.choice(len(rows), min(per_view, len(rows)), replace=False)
    u, v = cols[pick] + 0.5, rows[pick] + 0.5
    z = rng.uniform(*FLOATER_DEPTH, len(pick))
    cam_xyz = np.stack([(u - cams.cx[k]) / cams.fx[k] * z,
                        (v - cams.cy[k]) / cams.fy[k] * z, z], axis=1)
    points.append((cam_xyz - cams.translation[k]) @ cams.rotation[k])
    colors.append(scene.train.images[k][rows[pick], cols[pick]])
  floaters = np.concatenate(points)
  return dataclasses.replace(
      scene,
      points=np.concatenate([scene.points, floaters]).astype(
          scene.points.dtype),
      point_colors=np.concatenate([scene.point_colors] + colors).astype(
          scene.point_colors.dtype)), len(floaters)


def probe_config(steps: int, sem: config_lib.SemanticConfig
                 ) -> config_lib.Config:
  """SH degree 0, no densification, the semantic schedule scaled to steps."""
  return config_lib.Config(
      gaussians=config_lib.GaussiansConfig(sh_degree=0),
      densify=config_lib.DensifyConfig(start=steps, stop=steps),
      train=config_lib.TrainConfig(steps=steps, eval_every=steps,
                                   checkpoint_every=0, log_every=100),
      semantic=sem.scaled_to(steps))


def run_probe(scene, num_static: int, num_floaters: int,
              cfg: config_lib.Config, workdir: str) -> dict:
  """Trains and returns the probe's summary (see module docstring)."""
  cfg = train.resolve(cfg, scene)
  result = train.fit(cfg, scene, workdir,
                     scorer=guidance.make_scorer(cfg.semantic, scene),
                     progress=False)
  alive = np.asarray(result.state.alive)
  s = np.asarray(semantic.normalized_scores(result.state.semantic))
  n = np.asarray(result.state.semantic.n)
  out = {"test_psnr": result.curve[-1]["test_psnr"],
         "train_seconds": round(result.train_seconds, 1)}
  for name, rows in (("static", slice(0, num_static)),
                     ("floaters", slice(num_static,
                                        num_static + num_floaters))):
    keep = alive[rows]
    out[f"{name}_pruned"] = round(1.0 - float(keep.mean()), 4)
    if keep.any():
      out[f"{name}_s_q10_50_90_99"] = np.round(
          np.quantile(s[rows][keep], [0.1, 0.5, 0.9, 0.99]), 4).tolist()
      out[f"{name}_n_median"] = round(float(np.median(n[rows][keep])), 1)
  return out


_WEIGHTING = flags.DEFINE_enum("weighting", "visibility",
                               list(config_lib.WEIGHTINGS),
                               "SemanticConfig.weighting.")
_TAU = flags.DEFINE_float("tau", 1.0, "Prune threshold (1.0: no score "
                          "prune).")
_N_MIN = flags.DEFINE_float("n_min", 10.0, "SemanticConfig.n_min.")
_SCORE_EVERY = flags.DEFINE_integer("score_every", 1,
                                    "SemanticConfig.score_every.")
_STEPS = flags.DEFINE_integer("steps", 400, "Training steps.")
_DOWNSCALE = flags.DEFINE_integer("downscale", 2, "Image downscale.")
_PER_VIEW = flags.DEFINE_integer("per_view", 100, "Floaters per view.")
_WORKDIR = flags.DEFINE_string("workdir", "/tmp/floater_scores",
                               "Scratch folder for the checkpoint.")


def main(argv):
  del argv
  scene = scene_lib.load_scene(default_scene.ensure_default_scene(),
                               downscale=_DOWNSCALE.value)
  num_static = len(scene.points)
  scene, num_floaters = plant_floaters(scene, np.random.default_rng(0),
                                       _PER_VIEW.value)
  sem = config_lib.SemanticConfig(scorer="oracle", weighting=_WEIGHTING.value,
                                  tau=_TAU.value, n_min=_N_MIN.value,
                                  score_every=_SCORE_EVERY.value)
  summary = run_probe(scene, num_static, num_floaters,
                      probe_config(_STEPS.value, sem), _WORKDIR.value)
  print(json.dumps({"weighting": _WEIGHTING.value, "tau": _TAU.value,
                    "n_min": _N_MIN.value, "steps": _STEPS.value,
                    "score_every": _SCORE_EVERY.value,
                    "num_static": num_static, "num_floaters": num_floaters,
                    **summary}))


if __name__ == "__main__":
  cli.run(main)
