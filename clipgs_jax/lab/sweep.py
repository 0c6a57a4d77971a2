"""Runs a sweep: the rows x benchmarks of a config file's `sweep` section.

Each row is the base config plus the row's overrides, run in this process
(run.train_and_evaluate) into workdir/<benchmark>/<row>/ and collected into
a table (kinds: table, ablate, tau_sweep) or a side-by-side comparison
(demo). Rows resume, and a row whose metrics.json has its train.steps is
skipped when its config.json is the row's config (else the row fails: a
finished run of another seed or setting is never reported as this one).
"""

import json
import os
from typing import Any

from absl import app
from absl import logging
import ml_collections
import numpy as np

from clipgs_jax import checkpoint
from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax import config_file
from clipgs_jax import fileio
from clipgs_jax import plots
from clipgs_jax import run as run_lib
from clipgs_jax.lab import table
from clipgs_jax.lab import tau_sweep
from clipgs_jax.data import images as images_lib
from clipgs_jax.data import scene as scene_lib

KINDS = ("table", "ablate", "tau_sweep", "demo")


def _merge(base: dict, overrides: dict) -> dict:
  """`base` with `overrides` set into it, section by section."""
  out = dict(base)
  for key, value in overrides.items():
    if isinstance(value, dict) and isinstance(out.get(key), dict):
      value = _merge(out[key], value)
    out[key] = value
  return out


def _finished(workdir: str, steps: int) -> dict | None:
  """workdir/metrics.json when it has `steps` steps, else None."""
  try:
    with open(os.path.join(workdir, run_lib.METRICS_JSON)) as f:
      metrics = json.load(f)
  except (OSError, ValueError):
    return None
  return metrics if metrics.get("steps") == steps else None


def config_changes(workdir: str, cfg: config_lib.Config) -> list[str]:
  """'field: stored -> wanted' for each field where the run in `workdir`
  (its config.json) differs from `cfg`; scene_extent, which the run
  resolves from its scene, counts only when `cfg` sets it. A field the
  stored config lacks (written before the field existed) differs: that
  run did not have it, whatever its default is now."""
  path = os.path.join(workdir, run_lib.CONFIG_JSON)
  try:
    with open(path) as f:
      saved = json.load(f)
  except (OSError, ValueError) as e:
    return [f"{path} is unreadable ({e})"]
  if not isinstance(saved, dict):
    return [f"{path} is not a config"]
  saved, wanted = config_lib.migrate(saved), config_lib.to_dict(cfg)
  if not cfg.scene_extent > 0:
    saved.pop("scene_extent", None), wanted.pop("scene_extent")
  saved, wanted = (json.loads(json.dumps(d)) for d in (saved, wanted))
  return checkpoint.config_differences(saved, wanted)


def run_row(cfg: config_lib.Config, workdir: str, *,
            clip_weights: str | None, run_info: dict[str, Any]
            ) -> tuple[dict | None, str | None]:
  """Runs (or skips, when finished with the same config) one row; a user
  error, or a finished run of another config in its folder, fails the row.

  Returns:
    (metrics dict or None, error line or None).
  """
  metrics = _finished(workdir, cfg.train.steps)
  if metrics is not None:
    changes = config_changes(workdir, cfg)
    if changes:
      more = f" and {len(changes) - 3} more" if len(changes) > 3 else ""
      line = (f"{workdir} holds a finished run of another config "
              f"({'; '.join(changes[:3])}{more}); pass a new --workdir, or "
              "delete the folder to run it again")
      logging.error("row %s failed: %s", workdir, line)
      return None, line
    logging.info("skip %s: metrics.json already has %d steps", workdir,
                 cfg.train.steps)
    return metrics, None
  try:
    return run_lib.train_and_evaluate(
        cfg, workdir, resume=True, clip_weights=clip_weights,
        run_info=run_info), None
  except cli.USER_ERRORS as e:
    line = cli.error_line(e)
    logging.error("row %s failed: %s", workdir, line)
    return None, line


def _names(text: str) -> list[str]:
  return [t.strip() for t in str(text or "").split(",") if t.strip()]


def command_line_keys(argv) -> set[str]:
  """The config keys that `--config.KEY=VALUE` arguments in argv set."""
  keys = set()
  for arg in argv or ():
    if arg.startswith("--config."):
      keys.add(arg[len("--config."):].split("=", 1)[0])
  return keys


def check_row_overrides(cd: ml_collections.ConfigDict, rows: list[str],
                        keys: set[str]) -> None:
  """Refuses a command-line override that a row's own override replaces.

  A row's overrides win over the base config, command line included, so
  `--config.pixel.loss_masking=False` would not reach a row that sets
  it (the residual rows set True): one line naming the row and the key.
  """
  for row in rows:
    pinned = cd.sweep.row_overrides.get(row)
    if pinned is None:
      continue
    pinned = pinned.to_dict()
    for key in sorted(keys):
      section, _, field = key.partition(".")
      values = pinned.get(section)
      if not (isinstance(values, dict) and field in values):
        continue
      if values[field] != cd[section][field]:
        raise app.UsageError(
            f"--config.{key}={cd[section][field]} does not reach row {row!r},"
            f" which sets {key}={values[field]}; leave that row out of "
            "--config.sweep.rows or drop the flag")


def row_config(cd: ml_collections.ConfigDict, row: str,
               scene: str | None = None, **overrides) -> config_lib.Config:
  """The checked Config of a sweep's row: the base config (cd without its
  sweep section), then cd.sweep.row_overrides[row], then `overrides`
  (sections of values), on `scene` (None: the embedded scene)."""
  rows = cd.sweep.row_overrides
  if row not in rows:
    raise app.UsageError(f"--config.sweep.rows: unknown row {row!r}; "
                         f"choose from {', '.join(sorted(rows))}")
  values = cd.to_dict()
  del values["sweep"]
  values = _merge(_merge(values, rows[row].to_dict()), overrides)
  values["data"] = dict(values["data"], scene=scene)
  return config_file.check(values)


def _settings(cfg: config_lib.Config, clip_weights: str | None,
              run_info: dict) -> dict:
  """The settings every row of a sweep shares, for table.md / .json."""
  return {
      "config": run_info.get("config", "?"),
      "steps": cfg.train.steps, "downscale": cfg.data.downscale,
      "seed": cfg.train.seed, "tau": cfg.semantic.tau,
      "semantic_weighting": cfg.semantic.weighting,
      "tile_budget": cfg.render.tile_budget,
      "lpips_net": cfg.eval.lpips_net,
      "clip_weights": clip_weights or "(none: no clip rows)",
      **table.machine_and_date()}


def _short_label(cfg: config_lib.Config) -> str:
  """A panel title: what a demo row's map needs (run.semantic_label says
  it in full)."""
  sem = cfg.semantic
  if not sem.enabled:
    return "vanilla 3DGS"
  if sem.scorer in ("oracle", "uniform", "oracle_patch"):
    return "ORACLE-PIXEL (ground truth)" if sem.scorer == "oracle" else (
        sem.scorer.upper())
  name = {"clip": "dense CLIP", "learned": "learned map"}.get(
      sem.scorer, "residual map")
  if sem.scorer == "clip" and cfg.residual.with_semantic:
    name += " + residual"
  return (name + (" + features" if cfg.residual.features else "")
          + (", remembered" if cfg.residual.remember else ""))


def demo_view(psnr: dict, oracle: dict) -> int:
  """The test view a demo's picture shows: where the transients cost
  vanilla (the first row) most, i.e. where an oracle row (`oracle[row]`)
  gains most over it; without one, where the second row changes PSNR most
  against vanilla; with one row, its worst view. `psnr`: row -> per-view
  test PSNR, in row order."""
  rows = list(psnr)
  if len(rows) == 1:
    return int(np.argmin(psnr[rows[0]]))
  reference = next((k for k in rows[1:] if oracle[k]), rows[1])
  gain = psnr[reference] - psnr[rows[0]]
  return int(np.argmax(gain if oracle[reference] else np.abs(gain)))


def _demo_outputs(workdir: str, cfgs: dict, metrics: dict) -> dict:
  """comparison.png and comparison.json of the demo's runs.

  The rows are vanilla first, then the row the demo shows (the best one
  that needs nothing but the photos, or dense CLIP with weights), then any
  reference rows (ORACLE-PIXEL); the picture is one test view, one panel
  per row and the ground truth, each titled with its label and PSNR there:
  `demo_view`'s.
  """
  rows = list(cfgs)
  _, _, scene = run_lib.load_run(os.path.join(workdir, rows[0]))
  names = scene.test.names
  psnr = {k: np.array([m["test"]["per_image"][n]["psnr"] for n in names])
          for k, m in metrics.items()}
  view = demo_view(psnr, {k: c.semantic.scorer == "oracle"
                          for k, c in cfgs.items()})
  stem = os.path.splitext(os.path.basename(names[view]))[0]
  renders = [images_lib.read_image(os.path.join(
      workdir, k, run_lib.TEST_RENDERS, stem + ".png")) for k in rows]
  plots.side_by_side(
      renders + [np.asarray(scene.test.images[view])],
      [f"{_short_label(cfgs[k])}: {psnr[k][view]:.2f} dB"
       for k in rows] + ["ground truth"],
      os.path.join(workdir, "comparison.png"))
  summary = {
      k: {"label": run_lib.semantic_label(cfgs[k]),
          "test_psnr": m["test"]["psnr"], "test_ssim": m["test"]["ssim"],
          "test_lpips": m["test"]["lpips"],
          "lpips_net": m["test"]["lpips_net"],
          "train_seconds": m["train_seconds"],
          "num_gaussians": m["num_gaussians"]}
      for k, m in metrics.items()}
  summary["view"] = names[view]
  fileio.write_json(os.path.join(workdir, "comparison.json"), summary)
  return summary


def run(cd: ml_collections.ConfigDict, workdir: str, *,
              clip_weights: str | None = None,
              run_info: dict[str, Any] | None = None) -> dict:
  """Every row of the sweep in cd.sweep, then its table or comparison.

  Every row's config is built and checked (config_file.check) before the first
  row runs; each row is one run.train_and_evaluate.

  Args:
    cd: the ConfigDict of a config file with a `sweep` section (with
      command-line overrides; --scene sets sweep.benchmarks).
    workdir: str, the root of the rows' folders.
    clip_weights: str or None, CLIP weights for clip rows.
    run_info: extra run.json fields (the config file, argv).
  Returns:
    {"rows": [...]} as in table.json (demo: comparison.json's dict).
  Raises:
    ValueError: after writing the table, when a row failed.
  """
  sweep = cd.sweep
  kind = sweep.kind
  cli.require(kind in KINDS, "config.sweep.kind", kind,
              f"is not one of {', '.join(KINDS)}")
  run_info = run_info or {}
  workdir = os.path.abspath(workdir)
  benchmarks = [os.path.abspath(b) for b in _names(sweep.benchmarks)]
  if kind == "demo":
    benchmarks = benchmarks or [None]
  cli.require(bool(benchmarks), "config.sweep.benchmarks", "",
              "is empty; pass --scene=BENCH[,BENCH...]")
  if kind == "demo":          # one scene; rows go to workdir/<row>
    cli.require(len(benchmarks) == 1, "scene", sweep.benchmarks,
                "names several scenes; the demo takes one")
    names = [""]
  else:
    names = [os.path.basename(b).removesuffix(scene_lib.PACK_SUFFIX)
             for b in benchmarks]
  cli.require(len(set(names)) == len(names), "scene", ",".join(names),
              "names two benchmarks of the same basename; rename one")
  rows = _names(sweep.rows)
  check_row_overrides(cd, rows, command_line_keys(run_info.get("argv")))
  plan = []    # (benchmark name, row, tau or None, Config)
  for bench, name in zip(benchmarks, names):
    for row in rows:
      extra = (sweep.clip_overrides.get(row, {}).to_dict()
               if kind == "demo" and clip_weights else {})
      cfg = row_config(cd, row, bench, **extra)
      plan.append((name, row, None, cfg))
    if kind == "tau_sweep":
      scorer = sweep.scorer
      for tau in _taus(sweep.taus):
        cfg = row_config(cd, scorer, bench, semantic={"tau": tau})
        plan.append((name, f"{scorer}_tau{tau:g}", tau, cfg))
  needs_clip = [p for p in plan if p[3].semantic.scorer == "clip"]
  if kind == "tau_sweep" and needs_clip and not clip_weights:
    raise app.UsageError("--config.sweep.scorer=clip needs --clip_weights")
  results = []
  for name, row, tau, cfg in plan:
    folder = os.path.join(workdir, name, row)
    metrics, error = None, None     # a clip row without weights: not run
    if cfg.semantic.scorer != "clip" or clip_weights:
      metrics, error = run_row(cfg, folder, clip_weights=clip_weights,
                               run_info=run_info)
    results.append(table.RowResult(name, row, tau, cfg, metrics, error,
                                   folder))
  out = os.path.abspath(sweep.get("out") or workdir)
  settings = _settings(plan[0][3], clip_weights, run_info)
  failed = [r for r in results if r.error]
  if kind == "demo":
    if failed:
      raise ValueError(f"demo: row {failed[0].row} failed "
                       f"({failed[0].error}); fix the cause and rerun to "
                       "resume")
    return _demo_outputs(workdir, {r.row: r.cfg for r in results},
                         {r.row: r.metrics for r in results})
  collected = _COLLECT[kind](results, settings, out, sweep.to_dict())
  if failed:
    names = ", ".join(f"{r.scene}/{r.row}" for r in failed)
    raise ValueError(f"sweep: rows {names} failed; the table marks them, "
                     "the log says why; rerun to resume")
  return collected


def _taus(text) -> list[float]:
  try:
    return [float(t) for t in _names(text)]
  except ValueError as e:
    raise app.UsageError(f"--config.sweep.taus={text} must be numbers, "
                         "comma-separated") from e


_COLLECT = {"table": table.write_table, "ablate": table.write_ablation,
            "tau_sweep": tau_sweep.write_sweep}
