"""Where localized evidence fails: s_j of billboard ghosts against the rest.

A diagnostic for persistent benchmarks (a transients.json with billboards),
behind `experiments/report.py --report=evidence`. Every training view of a
finished run's final state is rendered with its ground-truth mask as the
evidence map, as ORACLE-PIXEL scores it, and each Gaussian's share of
blending weight on transient pixels is summed over the views under the two
rules training knows: "raw" (sum_i w_ij m_i / sum_i w_ij) and "agreement"
(the default; a transient pixel counts only as far as the render reproduces
the photo there, see semantic.agreement). The labels come from geometry, not
from any score: a ghost is a Gaussian whose mean lies on a billboard
(data.billboards.on_billboard). For each rule: histograms of s_j for ghost
and other rows, their medians, and the precision and recall of the prune rule
s_j > tau_p. A guided run's own accumulated s_j is summarised too.
"""

import functools
import json
import os

import jax
import jax.numpy as jnp
from matplotlib import figure
import numpy as np

from clipgs_jax import camera as camera_lib
from clipgs_jax import config as config_lib
from clipgs_jax import fileio
from clipgs_jax import plots
from clipgs_jax import run as run_lib
from clipgs_jax import semantic
from clipgs_jax.data import billboards
from clipgs_jax.render import project as project_lib
from clipgs_jax.render import rasterize

EVIDENCE_JSON = "evidence.json"
EVIDENCE_PNG = "evidence.png"


def ghost_rows(means, manifest: dict, views) -> np.ndarray:
  """bool [C], the rows whose mean lies on some billboard of `manifest`.

  Args:
    means: float [C, 3].
    manifest: a persistent benchmark's transients.json.
    views: data.scene.Views holding every view a billboard is seen from.
  """
  boards = manifest.get("billboards")
  if not boards:
    raise ValueError(
        f"transients.json (mode {manifest.get('mode')!r}) has no billboards: "
        "ghost labels need a persistent benchmark (experiments/prepare.py "
        "--prepare=benchmark --mode=persistent).")
  index = {name: i for i, name in enumerate(views.names)}
  centres = camera_lib.camera_center(views.cameras)
  means = np.asarray(means, np.float64)
  out = np.zeros(len(means), bool)
  for board in boards:
    missing = [v for v in board["views"] if v not in index]
    if missing:
      raise ValueError(f"billboard {board['id']} is seen from {missing}, "
                       "which are not training views of this run; pass a "
                       "run trained on the benchmark's clutter split.")
    corners = np.asarray(board["corners"], np.float64)
    eyes = centres[[index[v] for v in board["views"]]]
    distance = float(np.mean(np.linalg.norm(eyes - corners.mean(0), axis=1)))
    out |= billboards.on_billboard(means, corners, distance)
  return out


@functools.lru_cache(maxsize=None)
def _view_fn(render_cfg: config_lib.RenderConfig):
  def fn(params, alive, cam, bg, degree, mask, photo):
    proj = project_lib.project(params, alive, cam, near=render_cfg.near,
                               sh_degree=degree)
    out = rasterize.rasterize(proj, cam, bg, render_cfg, evidence_map=mask)
    agree = semantic.agreement(out.image, photo)
    reproduced = rasterize.rasterize(proj, cam, bg, render_cfg,
                                     evidence_map=mask * agree).evidence
    pixels = jnp.stack([jnp.sum(agree * mask), jnp.sum(mask),
                        jnp.sum(agree * (1 - mask)), jnp.sum(1 - mask)])
    return (out.contribution, out.evidence, reproduced, pixels,
            out.num_overflow)
  return jax.jit(fn)


def pixel_evidence(params, alive, views, cfg: config_lib.Config
                   ) -> dict[str, np.ndarray]:
  """Per-row sums over every view of `views`, with its mask as the map.

  Returns:
    float64 [C] arrays: "weight" (sum w), "raw" (sum w m), "reproduced"
    (sum w m a, a = semantic.agreement of the render with the photo); and
    float64 [4] "pixels": sum of a and count over transient pixels, the
    same over the other pixels.
  """
  if views.masks is None:
    raise ValueError("the views have no masks: pixel evidence needs the "
                     "benchmark's ground-truth masks/ (clutter split).")
  fn = _view_fn(cfg.render)
  bg = jnp.asarray(cfg.train.background, jnp.float32)
  degree = jnp.asarray(params.sh_degree, jnp.int32)
  cams = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), views.cameras)
  sums = {k: np.zeros(params.capacity) for k in ("weight", "raw",
                                                 "reproduced")}
  sums["pixels"] = np.zeros(4)
  dropped = 0
  for i in range(len(views)):
    outs = fn(params, alive, camera_lib.camera_at(cams, i), bg, degree,
              jnp.asarray(views.masks[i], jnp.float32),
              jnp.asarray(views.images[i]))
    for key, value in zip(sums, outs[:4]):
      sums[key] += np.asarray(value, np.float64)
    dropped += int(outs[4])
  if dropped:
    raise ValueError(f"{dropped} tile-list entries dropped over "
                     f"{len(views)} views: the sums would be inexact; raise "
                     "render.tile_budget.")
  return sums


def summarize(scores, weight, ghost, alive, tau: float, bins: int) -> dict:
  """Histograms and prune-rule quality of s_j for ghost and other rows.

  Only alive rows with weight >= semantic.MIN_EVIDENCE_WEIGHT count (the
  rows the prune rule judges).

  Returns:
    {"edges", "ghost" and "other" (counts, median, num, above_tau), "tau",
    "precision" and "recall" of s_j > tau (None when undefined)}.
  """
  judged = np.asarray(alive) & (np.asarray(weight)
                                >= semantic.MIN_EVIDENCE_WEIGHT)
  edges = np.linspace(0.0, 1.0, bins + 1)
  out = {"edges": edges.tolist(), "tau": tau}
  for name, rows in (("ghost", judged & ghost), ("other", judged & ~ghost)):
    s = np.clip(np.asarray(scores)[rows], 0.0, 1.0)
    out[name] = {"num": int(rows.sum()),
                 "counts": np.histogram(s, edges)[0].tolist(),
                 "median": float(np.median(s)) if s.size else None,
                 "above_tau": int(np.sum(s > tau))}
  above = out["ghost"]["above_tau"] + out["other"]["above_tau"]
  out["precision"] = out["ghost"]["above_tau"] / above if above else None
  out["recall"] = (out["ghost"]["above_tau"] / out["ghost"]["num"]
                   if out["ghost"]["num"] else None)
  return out


def _share(part: float, whole: float) -> float | None:
  return float(part / whole) if whole > 0 else None


def _ratio(num, den):
  return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def evidence_report(workdir: str, bins: int = 10) -> dict:
  """Writes DIR/evidence.json and DIR/evidence.png for a finished run.

  Args:
    workdir: a run folder (with its checkpoint) trained on the clutter
      split of a persistent benchmark.
    bins: histogram bins on [0, 1].
  """
  if bins < 1:
    raise ValueError(f"bins must be >= 1, got {bins}.")
  run, cfg, scene, state = run_lib.load_state(workdir)
  path = os.path.join(run["scene"], "transients.json")
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{path} is missing: the run's scene is not a "
                            "benchmark written by experiments/prepare.py.")
  with open(path) as f:
    manifest = json.load(f)
  alive = np.asarray(state.alive)
  ghost = ghost_rows(state.params.means, manifest, scene.train) & alive
  sums = pixel_evidence(state.params, state.alive, scene.train, cfg)
  tau = cfg.pixel.tau_p
  agreed_weight = semantic.agreement_weight(
      sums["weight"], sums["raw"], sums["reproduced"], xnp=np)
  rules = {
      "raw": summarize(_ratio(sums["raw"], sums["weight"]), sums["weight"],
                       ghost, alive, tau, bins),
      "agreement": summarize(_ratio(sums["reproduced"], agreed_weight),
                             agreed_weight, ghost, alive, tau, bins)}
  stats = state.semantic
  own = None
  if cfg.semantic.localized and float(jnp.sum(stats.weight)) > 0:
    own = summarize(np.asarray(semantic.normalized_scores(stats)),
                    np.asarray(stats.weight), ghost, alive, tau, bins)
  total = sums["weight"][alive].sum()
  masked = sums["raw"][alive].sum()
  out = {
      "workdir": os.path.abspath(workdir), "scene": run["scene"],
      "step": int(state.step), "num_views": len(scene.train),
      "num_alive": int(alive.sum()), "num_ghost": int(ghost.sum()),
      # Of all blending weight, of the weight on transient pixels: the
      # ghosts' share; and how well the render reproduces the transient
      # pixels (weight-averaged agreement), i.e. whether they are fitted.
      "ghost_weight_share": _share(sums["weight"][ghost].sum(), total),
      "ghost_masked_share": _share(sums["raw"][ghost].sum(), masked),
      "masked_agreement": _share(sums["reproduced"][alive].sum(), masked),
      # Per pixel, unweighted: the mean agreement on transient pixels
      # against that on the rest (how well the run fits the scene).
      "pixel_agreement": {
          "transient": _share(*sums["pixels"][:2]),
          "static": _share(*sums["pixels"][2:])},
      "ghost_rule": {"depth": billboards.GHOST_DEPTH,
                     "margin": billboards.GHOST_MARGIN},
      "min_evidence_weight": semantic.MIN_EVIDENCE_WEIGHT,
      "rules": rules, "run_scores": own}
  fileio.write_json(os.path.join(workdir, EVIDENCE_JSON), out)
  _plot(out, os.path.join(workdir, EVIDENCE_PNG))
  return out


def _plot(result: dict, out_path: str) -> None:
  panels = {f"{k} (ground-truth masks)": v
            for k, v in result["rules"].items()}
  if result["run_scores"] is not None:
    panels["the run's own s_j"] = result["run_scores"]
  fig = figure.Figure(figsize=(4.2 * len(panels), 3.2))
  for ax, (title, block) in zip(fig.subplots(1, len(panels), squeeze=False)[0],
                                panels.items()):
    edges = np.asarray(block["edges"])
    for name, colour in (("ghost", "tab:red"), ("other", "tab:grey")):
      counts = np.asarray(block[name]["counts"], float)
      ax.stairs(np.maximum(counts, 0.5), edges, color=colour,
                label=f"{name} ({block[name]['num']:,})")
    ax.axvline(block["tau"], color="k", lw=0.8, ls="--")
    ax.set_yscale("log")
    ax.set_ylim(bottom=0.5)
    ax.set_xlabel("s_j")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
  fig.axes[0].set_ylabel("Gaussians")
  plots.save_figure(fig, out_path)
