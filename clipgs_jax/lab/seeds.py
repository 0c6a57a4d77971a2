"""One benchmark table over several seeds: how far a cell moves by seed alone.

A table root (configs/table.py) holds ROOT/<benchmark>/<row>/ for one
`train.seed`. Given the roots of several seeds, every (benchmark, row) cell
gets its per-seed test PSNR, their mean, and its difference from the
cell's base row (vanilla; clean for a control row on the clean views)
paired by seed, since runs of one seed draw the same order of views. Per
benchmark it names the test views whose PSNR moves most between seeds of
one row: a handful of such views can decide a cell, and a difference
smaller than their spread is not a measurement. The same difference is
also taken over the other test views, and, for views set apart by name
(a region of the scene that one mechanism decides), over those views.
"""

import glob
import math
import os

import numpy as np

from clipgs_jax import run as run_lib
from clipgs_jax.lab import table

UNSTABLE_VIEWS = 3   # test views named per benchmark as the least stable


def find_runs(roots: list[str]) -> list[dict]:
  """Every finished run under the table roots, as dicts.

  Args:
    roots: folders, each ROOT/<benchmark>/<row>/ with metrics.json and
      config.json.

  Returns:
    list of {"benchmark", "row", "seed", "clean_views", "steps", "psnr",
    "per_view" ({test image: PSNR}), "precision", "recall", "seconds",
    "workdir"}.

  Raises:
    ValueError: naming the folder, when a root holds no finished run or
      two runs share a benchmark, row and seed.
  """
  runs, seen = [], {}
  for root in roots:
    found = sorted(glob.glob(os.path.join(root, "*", "*",
                                          run_lib.METRICS_JSON)))
    if not found:
      raise ValueError(f"{root}: no <benchmark>/<row>/"
                       f"{run_lib.METRICS_JSON}; pass the --workdir of a "
                       "table run (configs/table.py)")
    for path in found:
      workdir = os.path.dirname(path)
      metrics = run_lib.read_json(path, "test metrics")
      cfg = run_lib.load_config(workdir)
      bench, row = (os.path.basename(os.path.dirname(workdir)),
                    os.path.basename(workdir))
      cell = table.collect_row(bench, row, cfg, metrics)
      run = {"benchmark": bench, "row": row, "seed": cfg.train.seed,
             "clean_views": cell["clean_views"], "steps": cell["steps"],
             "psnr": cell["psnr"],
             "per_view": {k: v["psnr"] for k, v in
                          ((metrics.get("test") or {}).get("per_image")
                           or {}).items()},
             "precision": cell["map_precision"],
             "recall": cell["map_recall"],
             "seconds": cell["train_seconds"], "workdir": workdir}
      key = (run["benchmark"], run["row"], run["seed"])
      if key in seen:
        raise ValueError(f"{workdir} and {seen[key]} are both seed "
                         f"{key[2]} of {key[1]} on {key[0]}; pass one")
      seen[key] = workdir
      runs.append(run)
  return runs


def _mean(xs: list) -> float | None:
  xs = [x for x in xs if x is not None]
  return sum(xs) / len(xs) if xs else None


def _std_error(xs: list[float]) -> float | None:
  """The standard error of the mean of xs (None under two values)."""
  if len(xs) < 2:
    return None
  return float(np.std(xs, ddof=1) / math.sqrt(len(xs)))


def unstable_views(runs: list[dict], count: int = UNSTABLE_VIEWS
                   ) -> list[tuple[str, float]]:
  """The test views whose PSNR moves most between seeds of one row.

  Returns:
    [(view, spread)], largest first: spread is the root mean square over
    rows of the view's standard deviation across that row's seeds (rows
    with one seed left out).
  """
  by_row = {}
  for run in runs:
    by_row.setdefault(run["row"], []).append(run["per_view"])
  variances = {}
  for per_views in by_row.values():
    if len(per_views) < 2:
      continue
    for view in set.intersection(*(set(p) for p in per_views)):
      variances.setdefault(view, []).append(
          float(np.var([p[view] for p in per_views], ddof=1)))
  spread = {v: math.sqrt(sum(x) / len(x)) for v, x in variances.items()}
  return sorted(spread.items(), key=lambda kv: (-kv[1], kv[0]))[:count]


def _check_set_apart(runs: list[dict], set_apart: list[str]) -> None:
  """Raises ValueError unless every view set apart is a test view of every
  run."""
  for run in runs:
    missing = [v for v in set_apart if v not in run["per_view"]]
    if missing:
      raise ValueError(
          f"--set_apart: {', '.join(missing)} is not a test view of "
          f"{run['workdir']} (its views: {', '.join(sorted(run['per_view']))}"
          f"); name test views that every benchmark of --runs has")


def seed_table(runs: list[dict], num_unstable: int = UNSTABLE_VIEWS,
               set_apart: list[str] | None = None) -> dict:
  """The cells of the runs over their seeds, and each benchmark's views.

  Args:
    runs: find_runs' list.
    num_unstable: how many of each benchmark's least stable test views
      to name and, without set_apart, to leave out of "delta_other_views".
    set_apart: test views (image names) to leave out of
      "delta_other_views" instead, with their own "delta_set_apart".

  Returns:
    {"cells": [{"benchmark", "row", "base", "seeds", "psnr" (per seed),
    "mean", "delta" (paired with the base row, per seed it shares),
    "mean_delta", "delta_std_error", "delta_other_views" (the paired
    difference over the test views not left out), "delta_set_apart" (over
    the views set apart; None without them), "precision", "recall",
    "seconds" (means)}], "unstable": {benchmark: [(view, spread)]},
    "set_apart": the views set apart, or []}.

  Raises:
    ValueError: when the seeds of one cell ran different step counts, or
      a view set apart is not a test view of a run.
  """
  cells, unstable = [], {}
  set_apart = list(set_apart or [])
  _check_set_apart(runs, set_apart)
  for bench in sorted({r["benchmark"] for r in runs}):
    mine = [r for r in runs if r["benchmark"] == bench]
    unstable[bench] = unstable_views(mine, num_unstable)
    left_out = set(set_apart) or {v for v, _ in unstable[bench]}
    by_row = {}
    for run in sorted(mine, key=lambda r: r["seed"]):
      by_row.setdefault(run["row"], {})[run["seed"]] = run
    order = [r for r in table.ROWS if r in by_row] + sorted(
        set(by_row) - set(table.ROWS))
    for row in order:
      seeds = by_row[row]
      steps = {r["steps"] for r in seeds.values()}
      if len(steps) > 1:
        raise ValueError(f"{row} on {bench} ran {sorted(steps)} steps over "
                         "its seeds; a cell's seeds must share settings")
      first = next(iter(seeds.values()))
      base = table.CLEAN if first["clean_views"] else table.VANILLA
      base_runs = by_row.get(base, {}) if row != base else {}
      paired = [s for s in sorted(set(seeds) & set(base_runs))
                if seeds[s]["psnr"] is not None
                and base_runs[s]["psnr"] is not None]
      delta = {s: seeds[s]["psnr"] - base_runs[s]["psnr"] for s in paired}

      def views_delta(keep):
        """The paired difference of the mean PSNR over views `keep` takes."""
        out = []
        for s in paired:
          mine_mean, base_mean = (
              _mean([p for v, p in run["per_view"].items() if keep(v)])
              for run in (seeds[s], base_runs[s]))
          if mine_mean is not None and base_mean is not None:
            out.append(mine_mean - base_mean)
        return _mean(out)
      cells.append({
          "benchmark": bench, "row": row,
          "base": base if paired else None,
          "seeds": sorted(seeds),
          "psnr": {s: r["psnr"] for s, r in seeds.items()},
          "mean": _mean([r["psnr"] for r in seeds.values()]),
          "delta": delta, "mean_delta": _mean(list(delta.values())),
          "delta_std_error": _std_error(list(delta.values())),
          "delta_other_views": views_delta(lambda v: v not in left_out),
          "delta_set_apart": (views_delta(lambda v: v in left_out)
                              if set_apart else None),
          "precision": _mean([r["precision"] for r in seeds.values()]),
          "recall": _mean([r["recall"] for r in seeds.values()]),
          "seconds": _mean([r["seconds"] for r in seeds.values()])})
  return {"cells": cells, "unstable": unstable, "set_apart": set_apart}


def format_markdown(result: dict) -> str:
  """The seed table as Markdown, one line per benchmark on its views."""
  f = table.fmt
  apart = result["set_apart"]
  lines = [
      "| benchmark | row | seeds | PSNR per seed | mean | Δ per seed | "
      "mean Δ ± s.e. | Δ, other views | " + ("Δ, set apart | " if apart
                                             else "") + "map P / R | train s |",
      "|---|---|---|---|---:|---|---:|---:|" + ("---:|" if apart else "")
      + "---:|---:|"]
  for c in result["cells"]:
    per_seed = " / ".join(f(c["psnr"][s], ".2f") for s in c["seeds"])
    delta = " / ".join(f(c["delta"][s], "+.2f") for s in sorted(c["delta"]))
    mean_delta = f(c["mean_delta"], "+.2f", "—")
    if c["delta_std_error"] is not None:
      mean_delta += f" ± {c['delta_std_error']:.2f}"
    pr = ("—" if c["recall"] is None else
          f"{f(c['precision'], '.2f')} / {c['recall']:.2f}")
    lines.append(
        f"| {c['benchmark']} | {c['row']} | "
        f"{','.join(map(str, c['seeds']))} | {per_seed} | "
        f"{f(c['mean'], '.2f')} | {delta or '—'} | {mean_delta} | "
        f"{f(c['delta_other_views'], '+.2f', '—')} | "
        + (f"{f(c['delta_set_apart'], '+.2f', '—')} | " if apart else "")
        + f"{pr} | "
        f"{f(c['seconds'], '.0f')} |")
  lines.append("")
  lines.append("Δ: the row minus its base (vanilla, or clean for a control "
               "row) of the same seed. Δ, other views: the same over the "
               "test views left after " + (
                   f"those set apart ({', '.join(apart)}); Δ, set apart: "
                   "over those views." if apart else
                   "the least stable ones below."))
  for bench, views in result["unstable"].items():
    named = ", ".join(f"{v} ({s:.2f} dB)" for v, s in views) or "(one seed)"
    lines.append(f"- {bench}: the test views that move most between seeds "
                 f"of one row (s.d.): {named}")
  return "\n".join(lines) + "\n"
