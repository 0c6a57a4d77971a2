"""Prune-threshold sweep: quality and fraction pruned per tau, s_j histogram.

  python experiments/calibrate_tau.py --benchmark=DIR --workroot=DIR
      --steps=N [--downscale=K] [--seed=S] [--taus=0.3,0.02,0.015,0.01]
      [--semantic=oracle|clip] [--clip_weights=PATH]
      [--semantic_weighting=visibility|contribution] [--lpips_net=alex|vgg]
      [--extra_flags="--tile_budget=8192 ..."] [--out=DIR]

One guided train.py run per tau into workroot/<scene>/<scorer>_tau<T>/,
next to the vanilla row of experiments/table.py (workroot/<scene>/vanilla,
run here too when missing), with the table's settings: same steps,
downscale, seed, extra flags, the paper's schedule scaled to --steps. Runs
are resumable as the table's are.

Writes into --out (default workroot/<scene>), atomically:
  calibrate_tau.md / .json  tau, PSNR, ΔPSNR against vanilla, SSIM, LPIPS,
                            Gaussians, fraction pruned (by score and by the
                            n_min/alpha_min rule)
  s_j_histogram.png         the s_j histogram of the alive Gaussians at the
                            first prune (every tau's run is the same program
                            up to there) with each tau marked, and each
                            run's histogram before its last prune.
s_j = mean of beta * max(0, s_hat_d - 0.5) cannot exceed beta / 2 (0.05
with the paper's beta), so a tau above that prunes nothing by score. The
JSON also reports Otsu's threshold of the first-prune histogram as an
automatic rule (computed, not run: pass it back as --taus to test it).
"""

import json
import os
import shlex

from absl import app
from absl import flags
from absl import logging
import matplotlib
matplotlib.use("Agg")   # files only
import matplotlib.pyplot as plt  # pylint: disable=g-import-not-at-top,wrong-import-position
import numpy as np  # pylint: disable=g-import-not-at-top,wrong-import-position

from clipgs_jax import cli  # pylint: disable=g-import-not-at-top,wrong-import-position
from clipgs_jax import fileio  # pylint: disable=g-import-not-at-top,wrong-import-position
from clipgs_jax import plots  # pylint: disable=g-import-not-at-top,wrong-import-position
import table  # pylint: disable=g-import-not-at-top,wrong-import-position

FLAGS = flags.FLAGS
PAPER_TAUS = ("0.3", "0.02", "0.015", "0.01")


def _define_flags() -> None:
  table.define_run_flags()
  flags.DEFINE_string("benchmark", None, "Benchmark scene folder.")
  flags.DEFINE_list("taus", list(PAPER_TAUS), "Prune thresholds to run.")
  flags.DEFINE_enum("semantic", "oracle", ["oracle", "clip"],
                    "Scorer of the guided runs.")
  flags.DEFINE_string("clip_weights", None, "CLIP weights (--semantic=clip).")
  flags.DEFINE_string("out", None, "Output folder (default "
                      "workroot/<scene>).")
  flags.mark_flags_as_required(["benchmark"])


def otsu_threshold(histogram, edges) -> float | None:
  """Otsu's threshold of a histogram: the bin edge that maximises the
  between-class variance (the middle one of a tie); None for an empty or
  single-bin histogram.

  Args:
    histogram: float [B] counts.
    edges: float [B + 1] bin edges.
  """
  h = np.asarray(histogram, np.float64)
  centres = 0.5 * (np.asarray(edges[:-1]) + np.asarray(edges[1:]))
  total = h.sum()
  if total <= 0 or np.count_nonzero(h) < 2:
    return None
  w0 = np.cumsum(h)[:-1] / total          # class "<= edge k + 1"
  m = np.cumsum(h * centres)[:-1] / total
  mean = m[-1] + h[-1] * centres[-1] / total
  w1 = 1.0 - w0
  with np.errstate(divide="ignore", invalid="ignore"):
    between = (mean * w0 - m) ** 2 / (w0 * w1)
  between = np.where((w0 > 0) & (w1 > 0), between, -1.0)
  # Every edge inside an empty gap between the modes ties: take the middle.
  ties = np.flatnonzero(between >= between.max() * (1.0 - 1e-9))
  return float(edges[ties[len(ties) // 2] + 1])


def read_prune_events(workdir: str) -> dict | None:
  try:
    with open(os.path.join(workdir, "prune_events.json")) as f:
      return json.load(f)
  except (OSError, ValueError):
    return None


def sweep_row(tau: float, metrics: dict | None, error: str | None,
              vanilla_psnr: float | None) -> dict:
  """One row of the sweep from a guided run's metrics.json."""
  r = table.collect_row("", "oracle", metrics, error)
  semantic = (metrics or {}).get("semantic") or {}
  alive = r["num_gaussians"]
  by_score = semantic.get("num_pruned_semantic")
  by_rule = semantic.get("num_pruned_visibility")
  total = (by_score or 0) + (by_rule or 0) + (alive or 0)
  return {
      "tau": tau, "status": r["status"], "error": r["error"],
      "method": r["method"], "psnr": r["psnr"], "ssim": r["ssim"],
      "lpips": r["lpips"], "lpips_net": r["lpips_net"],
      "train_seconds": r["train_seconds"], "num_gaussians": alive,
      "fraction_pruned": r["fraction_pruned"],
      "fraction_pruned_by_score": by_score / total if total else None,
      "fraction_pruned_by_rule": by_rule / total if total else None,
      "delta_psnr": (r["psnr"] - vanilla_psnr
                     if r["psnr"] is not None and vanilla_psnr is not None
                     else None)}


def format_markdown(rows: list[dict], settings: dict) -> str:
  lines = ["# tau calibration", ""]
  lines += [f"- {k}: {v}" for k, v in settings.items()]
  net = rows[0]["lpips_net"] if rows and rows[0]["lpips_net"] else "?"
  lines += ["", "ΔPSNR: the run minus vanilla 3DGS (dB). Pruned by score: "
            "s_j > tau; by rule: n_j < n_min and alpha_j < alpha_min. "
            "Fractions of every Gaussian that ever lived past a prune.", "",
            f"| tau | PSNR | ΔPSNR | SSIM | LPIPS ({net}) | Gaussians | "
            "pruned | by score | by rule |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
  fmt = table._fmt  # pylint: disable=protected-access
  for r in rows:
    if r["status"] != "ok":
      lines.append(f"| {r['tau']} | FAILED ({r['error']}) |" + " — |" * 7)
      continue
    lines.append(
        f"| {r['tau']} | {fmt(r['psnr'], '.2f')} | "
        f"{fmt(r['delta_psnr'], '+.2f')} | {fmt(r['ssim'], '.4f')} | "
        f"{fmt(r['lpips'], '.4f')} | {fmt(r['num_gaussians'], 'd')} | "
        f"{fmt(r['fraction_pruned'], '.3f')} | "
        f"{fmt(r['fraction_pruned_by_score'], '.3f')} | "
        f"{fmt(r['fraction_pruned_by_rule'], '.3f')} |")
  return "\n".join(lines) + "\n"


def plot_histograms(events_by_tau: dict[float, dict], out_path: str) -> None:
  """s_j histograms (see module docstring), written atomically."""
  fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
  first = next((e for e in events_by_tau.values() if e and e["events"]),
               None)
  if first is None:
    raise ValueError("calibrate_tau: no run has a prune event; train longer "
                     "or check prune_start.")
  edges = np.asarray(first["histogram_edges"])
  e0 = first["events"][0]
  ax.stairs(e0["histogram"], edges, fill=True, alpha=0.3, color="grey",
            label=f"first prune (step {e0['step']})")
  for i, (tau, ev) in enumerate(sorted(events_by_tau.items())):
    color = f"C{i}"
    if ev and ev["events"] and sum(ev["events"][-1]["histogram"]) > 0:
      last = ev["events"][-1]
      ax.stairs(last["histogram"], edges, color=color,
                label=f"tau={tau}: before last prune (step {last['step']})")
    if tau <= edges[-1]:
      ax.axvline(tau, color=color, linestyle="--", label=f"tau={tau}")
    else:
      ax.annotate(f"tau={tau} > max s_j = {edges[-1]:g}: never reached",
                  (0.98, 0.95 - 0.06 * i), xycoords="axes fraction",
                  ha="right", fontsize=7, color=color)
  ax.set_yscale("symlog", linthresh=1.0)
  ax.set_xlabel("s_j (normalised distractor score)")
  ax.set_ylabel("alive Gaussians")
  ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.18),
            ncol=2)
  plots.save_figure(fig, out_path)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  if not os.path.isdir(FLAGS.benchmark):
    raise app.UsageError(f"--benchmark={FLAGS.benchmark} is not a folder.")
  try:
    taus = [float(t) for t in FLAGS.taus]
  except ValueError as e:
    raise app.UsageError(f"--taus must be numbers: {e}") from e
  if FLAGS.semantic == "clip" and not FLAGS.clip_weights:
    raise app.UsageError("--semantic=clip needs --clip_weights.")
  scene = table.scene_name(FLAGS.benchmark)
  root = os.path.join(os.path.abspath(FLAGS.workroot), scene)
  bench = os.path.abspath(FLAGS.benchmark)
  common = table.common_flags(FLAGS.downscale, FLAGS.seed, FLAGS.lpips_net)
  extra = shlex.split(FLAGS.extra_flags)
  vanilla, error = table.run_row(
      bench, os.path.join(root, "vanilla"), FLAGS.steps,
      common + table.row_flags("vanilla", tau=None, weighting="visibility",
                               clip_weights=None), extra)
  vanilla_psnr = (vanilla or {}).get("test", {}).get("psnr")
  if error:
    logging.error("vanilla row failed (%s); ΔPSNR left empty", error)
  rows, events = [], {}
  for tau in taus:
    workdir = os.path.join(root, f"{FLAGS.semantic}_tau{tau:g}")
    metrics, error = table.run_row(
        bench, workdir, FLAGS.steps,
        common + table.row_flags(FLAGS.semantic, tau=tau,
                                 weighting=FLAGS.semantic_weighting,
                                 clip_weights=FLAGS.clip_weights), extra)
    rows.append(sweep_row(tau, metrics, error, vanilla_psnr))
    events[tau] = read_prune_events(workdir)
  first = next((e for e in events.values() if e and e["events"]), None)
  otsu = (otsu_threshold(first["events"][0]["histogram"],
                         first["histogram_edges"]) if first else None)
  settings = {
      "benchmark": scene, "scorer": FLAGS.semantic, "steps": FLAGS.steps,
      "downscale": FLAGS.downscale, "seed": FLAGS.seed,
      "semantic_weighting": FLAGS.semantic_weighting,
      "extra_flags": FLAGS.extra_flags or "(none)",
      "vanilla_psnr": vanilla_psnr,
      "otsu_tau_first_prune (computed, not run)": otsu,
      **table.machine_and_date()}
  out = FLAGS.out or root
  os.makedirs(out, exist_ok=True)
  fileio.write_json(os.path.join(out, "calibrate_tau.json"),
                    {"settings": settings, "rows": rows})
  text = format_markdown(rows, settings)
  table.write_text(os.path.join(out, "calibrate_tau.md"), text)
  plot_histograms(events, os.path.join(out, "s_j_histogram.png"))
  print(text)


if __name__ == "__main__":
  _define_flags()
  cli.run(main)
