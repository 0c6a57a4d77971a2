"""Prune-threshold sweep: rows, Otsu's threshold, the s_j histogram plot."""

import json
import os

from matplotlib import figure
import numpy as np

from clipgs_jax import config as config_lib
from clipgs_jax import plots
from clipgs_jax import run as run_lib
from clipgs_jax.lab import table


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


def sweep_row(tau: float, cfg: config_lib.Config, metrics: dict | None,
              error: str | None, vanilla_psnr: float | None) -> dict:
  """One row of the sweep from a guided run's metrics.json dict."""
  r = table.collect_row("", f"tau{tau:g}", cfg, metrics, error)
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
  """calibrate_tau.md: the settings, then one Markdown row per tau."""
  lines = ["# tau calibration", ""]
  lines += [f"- {k}: {v}" for k, v in settings.items()]
  net = rows[0]["lpips_net"] if rows and rows[0]["lpips_net"] else "?"
  lines += ["", "ΔPSNR: the run minus vanilla 3DGS (dB). Pruned by score: "
            "s_j > tau; by rule: n_j < n_min and alpha_j < alpha_min. "
            "Fractions of every Gaussian that ever lived past a prune.", "",
            f"| tau | PSNR | ΔPSNR | SSIM | LPIPS ({net}) | Gaussians | "
            "pruned | by score | by rule |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
  fmt = table.fmt
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


def first_prune_otsu(events_by_tau: dict[float, dict | None]
                     ) -> float | None:
  """Otsu's threshold of the first prune's s_j histogram (every tau's run
  is the same program up to there); None without a prune event."""
  first = next((e for e in events_by_tau.values() if e and e["events"]),
               None)
  if first is None:
    return None
  return otsu_threshold(first["events"][0]["histogram"],
                        first["histogram_edges"])


def plot_histograms(events_by_tau: dict[float, dict | None],
                    out_path: str) -> None:
  """The s_j histogram of the alive Gaussians at the first prune with each
  tau marked, and each run's histogram before its last prune; written
  atomically.

  Args:
    events_by_tau: {tau: the run's prune_events.json dict, or None}.
    out_path: str, the PNG.
  """
  first = next((e for e in events_by_tau.values() if e and e["events"]),
               None)
  if first is None:
    raise ValueError("tau sweep: no run has a prune event; train longer "
                     "or check semantic.prune_start.")
  fig = figure.Figure(figsize=(7, 4), dpi=120)
  ax = fig.subplots()
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


def _read_events(workdir: str) -> dict | None:
  try:
    with open(os.path.join(workdir, run_lib.PRUNE_EVENTS_JSON)) as f:
      return json.load(f)
  except (OSError, ValueError):
    return None


def write_sweep(results: list[table.RowResult], settings: dict, out: str,
                sweep: dict) -> dict:
  """out/<benchmark>/calibrate_tau.md / .json and s_j_histogram.png from
  the vanilla row and one row per tau (their prune_events.json are read
  from the rows' folders). Returns {"settings", "rows"}."""
  every = []
  for name, group in table.by_scene(results).items():
    vanilla = next((r.metrics for r in group if r.row == table.VANILLA),
                   None)
    vanilla_psnr = table.test_psnr(vanilla)
    guided = [r for r in group if r.tau is not None]
    rows = [sweep_row(r.tau, r.cfg, r.metrics, r.error, vanilla_psnr)
            for r in guided]
    folder = os.path.join(out, name)
    events = {r.tau: _read_events(r.workdir) for r in guided}
    s = dict(settings, benchmark=name, scorer=sweep["scorer"],
             vanilla_psnr=vanilla_psnr)
    s["otsu_tau_first_prune (computed, not run)"] = first_prune_otsu(events)
    table.write_outputs(folder, "calibrate_tau", s, rows,
                        format_markdown(rows, s))
    plot_histograms(events, os.path.join(folder, "s_j_histogram.png"))
    every += rows
  return {"settings": settings, "rows": every}
