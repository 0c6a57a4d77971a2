"""Runs what a config file describes: one run, or a sweep of rows.

A config (configs/*.py) describes one run, or, with a `sweep` section, rows
x benchmarks: each row is the base config plus the row's overrides, run in
this process into workdir/<benchmark>/<row>/ and collected into a table
(kinds: table, ablate, tau_sweep) or a side-by-side comparison (demo).
Rows resume, and a row whose metrics.json has its train.steps is skipped.
"""

import dataclasses
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
from clipgs_jax import fileio
from clipgs_jax import guidance
from clipgs_jax import metrics as metrics_lib
from clipgs_jax import plots
from clipgs_jax import run as run_lib
from clipgs_jax import table
from clipgs_jax import tau_sweep
from clipgs_jax import train
from clipgs_jax.data import default_scene
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


def build(values: dict | ml_collections.ConfigDict) -> config_lib.Config:
  """The checked Config of one run; a bad value raises app.UsageError.

  train.steps None means default_scene.TRAIN_STEPS on the embedded scene
  (data.scene None) and TrainConfig's 30k on a scene folder. Nothing is
  read but the scene's existence.
  """
  if isinstance(values, ml_collections.ConfigDict):
    values = values.to_dict()
  embedded = (values.get("data") or {}).get("scene") is None
  auto = (default_scene.TRAIN_STEPS if embedded
          else config_lib.TrainConfig.steps)
  try:
    cfg = config_lib.from_config_dict(values, auto_steps=auto)
  except ValueError as e:
    raise app.UsageError(str(e)) from e
  try:
    guidance.validate(cfg.semantic)
  except ValueError as e:
    raise app.UsageError(f"--config.semantic: {e}") from e
  data, ev = cfg.data, cfg.eval
  cli.require(data.train_split in scene_lib.TRAIN_SPLITS,
              "config.data.train_split", data.train_split,
              f"is not one of {', '.join(scene_lib.TRAIN_SPLITS)}")
  nets = metrics_lib.LPIPS_NETS
  cli.require(ev.lpips_net in nets, "config.eval.lpips_net", ev.lpips_net,
              f"is not one of {', '.join(nets)}")
  if data.scene is not None and data.scene.endswith(scene_lib.PACK_SUFFIX):
    cli.require_file("scene", data.scene)
  else:
    cli.require_folder("scene", data.scene)
  if data.scene is None:
    return cfg
  # An absolute path, so that --resume from another folder matches.
  return dataclasses.replace(cfg, data=dataclasses.replace(
      data, scene=os.path.abspath(data.scene)))


def train_one(cfg: config_lib.Config, workdir: str, *, resume: bool = False,
              clip_weights: str | None = None,
              run_info: dict[str, Any] | None = None) -> dict:
  """Trains and evaluates one checked config (`build`) into `workdir`.

  Reads the checkpoint's metadata (resume), the scene and the CLIP
  weights before writing anything; a run that fails before its first
  checkpoint leaves no folder behind.

  Returns:
    The run's metrics.json dict.
  """
  workdir = os.path.abspath(workdir)
  ckpt_path = os.path.join(workdir, train.CHECKPOINT_NAME)
  resuming = resume and os.path.exists(ckpt_path)
  if resuming:
    checkpoint.read_meta(ckpt_path)      # a corrupt file fails here, early
  embedded = cfg.data.scene is None
  scene_path = (default_scene.ensure_default_scene() if embedded
                else cfg.data.scene)
  scene = scene_lib.load_scene(scene_path, downscale=cfg.data.downscale,
                               train_split=cfg.data.train_split)
  cfg = train.resolve(cfg, scene)
  if resuming:
    checkpoint.check_resumable(ckpt_path, cfg)
  height, width = scene.train.images.shape[1:3]
  logging.info("scene %s: %d train / %d test views, %dx%d, %d points, "
               "extent %.3f", scene_path, len(scene.train.names),
               len(scene.test.names), width, height, len(scene.points),
               scene.extent)
  try:
    scorer = guidance.make_scorer(cfg.semantic, scene,
                                  clip_weights=clip_weights)
  except (ValueError, FileNotFoundError) as e:
    raise app.UsageError(f"--config.semantic.scorer={cfg.semantic.scorer}: "
                         f"{e}") from e
  info = {"scene": os.path.abspath(scene_path), "embedded_scene": embedded,
          "downscale": cfg.data.downscale,
          "train_split": cfg.data.train_split, **(run_info or {})}
  with cli.output_dir(workdir, keep=train.CHECKPOINT_NAME):
    return run_lib.train_and_evaluate(
        cfg, scene, workdir, scorer=scorer, lpips_net=cfg.eval.lpips_net,
        resume=resume, run_info=info)


def _finished(workdir: str, steps: int) -> dict | None:
  """workdir/metrics.json when it has `steps` steps, else None."""
  try:
    with open(os.path.join(workdir, run_lib.METRICS_JSON)) as f:
      metrics = json.load(f)
  except (OSError, ValueError):
    return None
  return metrics if metrics.get("steps") == steps else None


def run_row(cfg: config_lib.Config, workdir: str, *,
            clip_weights: str | None, run_info: dict[str, Any]
            ) -> tuple[dict | None, str | None]:
  """Runs (or skips, when finished) one row; a user error fails the row.

  Returns:
    (metrics dict or None, error line or None).
  """
  metrics = _finished(workdir, cfg.train.steps)
  if metrics is not None:
    logging.info("skip %s: metrics.json already has %d steps", workdir,
                 cfg.train.steps)
    return metrics, None
  try:
    return train_one(cfg, workdir, resume=True, clip_weights=clip_weights,
                     run_info=run_info), None
  except cli.USER_ERRORS as e:
    line = cli.error_line(e)
    logging.error("row %s failed: %s", workdir, line)
    return None, line


def _names(text: str) -> list[str]:
  return [t.strip() for t in str(text or "").split(",") if t.strip()]


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
  return build(values)


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


def _demo_outputs(workdir: str, cfgs: dict, metrics: dict,
                  use_clip: bool) -> dict:
  """comparison.png and comparison.json of the demo's two runs."""
  _, _, scene = run_lib.load_run(os.path.join(workdir, "vanilla"))
  names = scene.test.names
  psnr = {k: np.array([m["test"]["per_image"][n]["psnr"] for n in names])
          for k, m in metrics.items()}
  # The test view where guidance changes PSNR most, to show what it does.
  view = int(np.argmax(np.abs(psnr["guided"] - psnr["vanilla"])))
  stem = os.path.splitext(os.path.basename(names[view]))[0]
  renders = [images_lib.read_image(os.path.join(
      workdir, k, run_lib.TEST_RENDERS, stem + ".png")) for k in cfgs]
  label = "guided, " + ("dense CLIP" if use_clip else "ORACLE-PIXEL")
  plots.side_by_side(
      renders + [np.asarray(scene.test.images[view])],
      [f"vanilla 3DGS: {psnr['vanilla'][view]:.2f} dB",
       f"{label}: {psnr['guided'][view]:.2f} dB", "ground truth"],
      os.path.join(workdir, "comparison.png"))
  summary = {
      k: {"label": run_lib.semantic_label(cfgs[k].semantic),
          "test_psnr": m["test"]["psnr"], "test_ssim": m["test"]["ssim"],
          "test_lpips": m["test"]["lpips"],
          "lpips_net": m["test"]["lpips_net"],
          "train_seconds": m["train_seconds"],
          "num_gaussians": m["num_gaussians"]}
      for k, m in metrics.items()}
  summary["view"] = names[view]
  fileio.write_json(os.path.join(workdir, "comparison.json"), summary)
  return summary


def run_sweep(cd: ml_collections.ConfigDict, workdir: str, *,
              clip_weights: str | None = None,
              run_info: dict[str, Any] | None = None) -> dict:
  """Every row of the sweep in cd.sweep, then its table or comparison.

  Every row's config is built and checked before the first row runs.

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
  plan = []    # (benchmark name, row, tau or None, Config)
  for bench, name in zip(benchmarks, names):
    for row in rows:
      extra = ({"semantic": {"scorer": "clip"}}
               if kind == "demo" and row != table.VANILLA and clip_weights
               else {})
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
                         {r.row: r.metrics for r in results},
                         bool(clip_weights))
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


def run(cd: ml_collections.ConfigDict, workdir: str, *,
        scene: str | None = None, resume: bool = False,
        clip_weights: str | None = None,
        run_info: dict[str, Any] | None = None) -> dict:
  """Runs the config file's one run or sweep into `workdir`.

  Args:
    cd: the ConfigDict (configs/*.py with command-line overrides).
    workdir: str, the run folder (a sweep: the root of its rows).
    scene: str or None, the scene folder (data.scene); a sweep: its
      benchmarks, comma-separated (sweep.benchmarks).
    resume: one run: continue from the folder's checkpoint (sweep rows
      always resume).
    clip_weights: str or None, CLIP weights for clip scorers.
    run_info: extra run.json fields (the config file, argv).
  Returns:
    One run: its metrics.json dict; a sweep: see `run_sweep`.
  """
  cd = ml_collections.ConfigDict(cd.to_dict())
  if "sweep" in cd:
    if scene is not None:
      cd.sweep.benchmarks = scene
    return run_sweep(cd, workdir, clip_weights=clip_weights,
                     run_info=run_info)
  if scene is not None:
    cd.data.scene = scene
  cfg = build(cd)
  return train_one(cfg, workdir, resume=resume, clip_weights=clip_weights,
                   run_info=run_info)
