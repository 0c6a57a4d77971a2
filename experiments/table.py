"""Benchmark table: vanilla, oracle, CLIP and clean-upper-bound 3DGS runs.

  python experiments/table.py --benchmarks=DIR[,DIR...] --workroot=DIR
      --steps=N [--downscale=K] [--seed=S] [--tau=T]
      [--semantic_weighting=visibility|contribution] [--lpips_net=alex|vgg]
      [--clip_weights=PATH] [--extra_flags="--tile_budget=8192 ..."]
      [--out=DIR]

Rows per benchmark (a RobustNeRF-layout scene from
make_transient_benchmark.py), each one experiments/train.py subprocess
into workroot/<benchmark basename>/<row>/ (log: train.log there):
  vanilla  --train_split=clutter --semantic=off
  oracle   --train_split=clutter --semantic=oracle --scale_semantic_schedule
           (the paper's image-level rule on ground-truth masks, not CLIP:
           the table labels it ORACLE)
  oracle_pixel         as oracle with --evidence=pixel (localized: the
           ground-truth mask per pixel, labelled ORACLE-PIXEL)
  oracle_pixel_masked  as oracle_pixel with --loss_masking
  clip     as oracle with --semantic=clip; only with --clip_weights
  clip_pixel  as clip with --evidence=pixel (dense CLIP); only with
           --clip_weights
  clean    --train_split=clean --semantic=off (the upper bound: the clean
           twins of the same training views)
Every row gets the same --steps --downscale --seed --lpips_net and
--extra_flags. Rows run with --resume, and a row whose metrics.json already
has --steps steps is skipped, so an interrupted table continues. A failed
row is kept in the table, marked failed, with its exit code.

Writes into --out (default --workroot), atomically: table.md (settings,
machine and date above a Markdown table) and table.json ({"settings",
"rows"}).
"""

import datetime
import json
import math
import os
import platform
import shlex
import subprocess
import sys

from absl import app
from absl import flags
from absl import logging

from clipgs_jax import cli
from clipgs_jax import fileio

FLAGS = flags.FLAGS

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TRAIN_SCRIPT = os.path.join(REPO_ROOT, "experiments", "train.py")

ROWS = ("vanilla", "oracle", "oracle_pixel", "oracle_pixel_masked", "clip",
        "clip_pixel", "clean")
GUIDED_ROWS = ("oracle", "oracle_pixel", "oracle_pixel_masked", "clip",
               "clip_pixel")
CLIP_ROWS = ("clip", "clip_pixel")
# Labels for rows without a metrics.json (failed); a finished guided row
# takes train.py's semantic label, which names the scorer too.
DEFAULT_LABELS = {
    "vanilla": "vanilla 3DGS (clutter)",
    "oracle": "CLIP-GS machinery, ORACLE scorer (ground-truth masks, not "
              "CLIP)",
    "oracle_pixel": "localized CLIP-GS machinery, ORACLE-PIXEL scorer",
    "oracle_pixel_masked": "localized CLIP-GS machinery, ORACLE-PIXEL "
                           "scorer, loss masking",
    "clip": "CLIP-GS (CLIP scorer)",
    "clip_pixel": "localized CLIP-GS (dense CLIP)",
    "clean": "3DGS on clean views (upper bound)",
}
# Lines of a failed row's train.log shown in the log and kept in the JSON.
LOG_TAIL_LINES = 30


def define_run_flags() -> None:
  """The flags of table.py, ablate.py and calibrate_tau.py that set where
  the rows go and what every train.py row of a benchmark shares."""
  flags.DEFINE_string("workroot", None, "Runs go to workroot/<scene>/<row>.")
  flags.DEFINE_integer("steps", None, "Training steps, every row.")
  flags.DEFINE_integer("downscale", 1, "Image downscale, every row.")
  flags.DEFINE_integer("seed", 0, "PRNG seed, every row.")
  flags.DEFINE_enum("semantic_weighting", "visibility",
                    ["visibility", "contribution"],
                    "Accumulation of the guided rows.")
  flags.DEFINE_enum("lpips_net", "alex", ["alex", "vgg"],
                    "LPIPS backbone, every row.")
  flags.DEFINE_string("extra_flags", "", "More train.py flags for every "
                      "row, one shell-quoted string.")
  flags.mark_flags_as_required(["workroot", "steps"])


def common_flags(downscale: int, seed: int, lpips_net: str) -> list[str]:
  """train.py flags every row of a benchmark gets (besides extra_flags)."""
  return [f"--downscale={downscale}", f"--seed={seed}",
          f"--lpips_net={lpips_net}"]


def scene_name(benchmark: str) -> str:
  """A benchmark's name: its folder's basename (workroot/<name>/<row>)."""
  return os.path.basename(os.path.normpath(benchmark))


def _define_flags() -> None:
  # Defined only when run as a script, so that tests can import this module
  # next to other experiment modules that define --steps, --tau, ...
  define_run_flags()
  flags.DEFINE_list("benchmarks", None, "Benchmark scene folders.")
  flags.DEFINE_float("tau", None, "Prune threshold for the guided rows "
                     "(default: train.py's, the paper's 0.015).")
  flags.DEFINE_string("clip_weights", None, "CLIP weights; adds the clip "
                      "row.")
  flags.DEFINE_string("out", None, "Folder for table.md / table.json "
                      "(default: --workroot).")
  flags.DEFINE_list("rows", None, f"Rows to run (default: all of "
                    f"{', '.join(ROWS)} that apply).")
  flags.mark_flags_as_required(["benchmarks"])


def row_names(clip_weights: str | None,
              only: list[str] | None = None) -> list[str]:
  """The rows of each benchmark, in table order (`only`: a subset)."""
  if only:
    unknown = set(only) - set(ROWS)
    if unknown:
      raise ValueError(f"unknown rows {sorted(unknown)}; choose from "
                       f"{', '.join(ROWS)}.")
  return [r for r in ROWS if (r not in CLIP_ROWS or clip_weights)
          and (not only or r in only)]


def row_flags(row: str, *, tau: float | None, weighting: str,
              clip_weights: str | None) -> list[str]:
  """train.py flags that tell row `row` apart from the others."""
  if row in ("vanilla", "clean"):
    split = "clutter" if row == "vanilla" else "clean"
    return [f"--train_split={split}", "--semantic=off"]
  if row not in GUIDED_ROWS:
    raise ValueError(f"unknown row {row!r}; choose one of {ROWS}.")
  scorer = "clip" if row in CLIP_ROWS else "oracle"
  out = ["--train_split=clutter", f"--semantic={scorer}",
         "--scale_semantic_schedule"]
  if row in ("oracle", "clip"):
    out.append(f"--semantic_weighting={weighting}")
    if tau is not None:
      out.append(f"--tau={tau}")
  else:
    out.append("--evidence=pixel")
  if row == "oracle_pixel_masked":
    out.append("--loss_masking")
  if scorer == "clip":
    out.append(f"--clip_weights={clip_weights}")
  return out


def read_metrics(workdir: str) -> dict | None:
  """workdir/metrics.json, or None when absent or unreadable."""
  path = os.path.join(workdir, "metrics.json")
  try:
    with open(path) as f:
      return json.load(f)
  except (OSError, ValueError):
    return None


def _finite(x) -> float | None:
  """x as a float, None for missing or non-finite values (JSON-safe)."""
  if x is None:
    return None
  x = float(x)
  return x if math.isfinite(x) else None


def collect_row(scene: str, row: str, metrics: dict | None,
                error: str | None = None) -> dict:
  """One table row from a run's metrics.json dict (None: the run failed).

  Args:
    scene: str, the benchmark name.
    row: str, one of ROWS.
    metrics: dict, train.py's metrics.json, or None.
    error: str, why the row failed (exit code, ...), or None.

  Returns:
    dict with "scene", "row", "method", "status" ("ok" or "failed"),
    "error", "psnr", "ssim", "lpips", "lpips_net", "train_seconds",
    "num_gaussians", "steps", "fraction_pruned" and "mask_iou" (the
    pruned Gaussians' rendered alpha against the transient masks; None for
    unguided rows and runs that pruned nothing); numbers are None where
    unknown or non-finite.
  """
  out = {"scene": scene, "row": row, "method": DEFAULT_LABELS[row],
         "status": "failed" if (error or metrics is None) else "ok",
         "error": error or (None if metrics is not None else "no metrics"),
         "psnr": None, "ssim": None, "lpips": None, "lpips_net": None,
         "train_seconds": None, "num_gaussians": None, "steps": None,
         "fraction_pruned": None, "mask_iou": None}
  if metrics is None:
    return out
  test = metrics.get("test", {})
  semantic = metrics.get("semantic")
  if row in GUIDED_ROWS and semantic and semantic.get("label"):
    out["method"] = semantic["label"]
  if row.startswith("oracle") and "ORACLE" not in out["method"]:
    # The oracle reads ground-truth masks; the table must never let it pass
    # for CLIP.
    out["method"] = "ORACLE: " + out["method"]
  out.update(
      psnr=_finite(test.get("psnr")), ssim=_finite(test.get("ssim")),
      lpips=_finite(test.get("lpips")), lpips_net=test.get("lpips_net"),
      train_seconds=_finite(metrics.get("train_seconds")),
      num_gaussians=metrics.get("num_gaussians"),
      steps=metrics.get("steps"))
  if row in GUIDED_ROWS and semantic:
    out["fraction_pruned"] = _finite(semantic.get("fraction_pruned"))
    iou = semantic.get("pruned_mask_iou") or {}
    out["mask_iou"] = _finite(iou.get("mean"))
  return out


def add_deltas(rows: list[dict]) -> list[dict]:
  """Adds "delta_psnr" (guided minus vanilla) and "gap_to_clean".

  gap_to_clean is clean PSNR minus the row's PSNR (dB; positive: below the
  upper bound), for the vanilla and guided rows. Either is None where a
  PSNR is missing or the row does not get one. Returns new dicts.
  """
  def psnr_of(scene, row):
    for r in rows:
      if r["scene"] == scene and r["row"] == row and r["status"] == "ok":
        return r["psnr"]
    return None

  out = []
  for r in rows:
    r = dict(r, delta_psnr=None, gap_to_clean=None)
    if r["psnr"] is not None and r["status"] == "ok":
      vanilla = psnr_of(r["scene"], "vanilla")
      clean = psnr_of(r["scene"], "clean")
      if r["row"] in GUIDED_ROWS and vanilla is not None:
        r["delta_psnr"] = r["psnr"] - vanilla
      if r["row"] != "clean" and clean is not None:
        r["gap_to_clean"] = clean - r["psnr"]
    out.append(r)
  return out


def _fmt(x, spec: str, missing: str = "n/a") -> str:
  return missing if x is None else format(x, spec)


def format_markdown(rows: list[dict], settings: dict) -> str:
  """table.md: the settings, then one Markdown row per table row.

  Args:
    rows: list of dicts from add_deltas(collect_row(...)).
    settings: dict; its items are listed above the table, and
      settings["lpips_net"] names the LPIPS column.

  Returns:
    str, the Markdown text.
  """
  nets = sorted({r["lpips_net"] for r in rows if r["lpips_net"]})
  net = ", ".join(nets) if nets else settings.get("lpips_net", "?")
  lines = ["# CLIP-GS benchmark table", ""]
  lines += [f"- {k}: {v}" for k, v in settings.items()]
  lines += [
      "", "Every row: the same steps, downscale, seed and extra flags. "
      "ΔPSNR: guided minus vanilla 3DGS on the same scene; gap to clean: "
      "clean upper bound minus the row (dB). The ORACLE row scores views "
      "with ground-truth masks, not CLIP. Mask IoU: the pruned Gaussians' "
      "rendered alpha (> 0.5) against the training views' transient "
      "masks.", "",
      f"| scene | method | PSNR | SSIM | LPIPS ({net}) | train s | "
      "Gaussians | fraction pruned | mask IoU | ΔPSNR | gap to clean |",
      "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
  for r in rows:
    if r["status"] != "ok":
      cells = [r["scene"], r["method"],
               f"FAILED ({r['error']})"] + ["—"] * 8
    else:
      guided = r["row"] in GUIDED_ROWS
      cells = [
          r["scene"], r["method"], _fmt(r["psnr"], ".2f"),
          _fmt(r["ssim"], ".4f"), _fmt(r["lpips"], ".4f"),
          _fmt(r["train_seconds"], ".1f"),
          _fmt(r["num_gaussians"], "d"),
          _fmt(r["fraction_pruned"], ".3f") if guided else "—",
          _fmt(r.get("mask_iou"), ".3f") if guided else "—",
          _fmt(r["delta_psnr"], "+.2f") if guided else "—",
          _fmt(r["gap_to_clean"], "+.2f") if r["row"] != "clean" else "—"]
    lines.append("| " + " | ".join(c.replace("|", "/") for c in cells)
                 + " |")
  return "\n".join(lines) + "\n"


def machine_and_date() -> dict:
  """The "machine" and "date" settings every benchmark output names."""
  return {"machine": f"{platform.node()}, {os.cpu_count()} cpus",
          "date": datetime.datetime.now().isoformat(timespec="seconds")}


def write_text(path: str, text: str) -> None:
  """Writes `text` to `path` atomically."""
  def write(tmp):
    with open(tmp, "w") as f:
      f.write(text)
  fileio.atomic_write(path, write, os.path.splitext(path)[1])


def _log_tail(path: str, n: int = LOG_TAIL_LINES) -> str:
  try:
    with open(path, errors="replace") as f:
      return "".join(f.readlines()[-n:])
  except OSError:
    return ""


def run_row(scene_dir: str, workdir: str, steps: int,
            common: list[str], extra: list[str]) -> tuple[dict | None,
                                                           str | None]:
  """Runs (or skips) one train.py row; host-only.

  Returns:
    (metrics dict or None, error str or None).
  """
  metrics = read_metrics(workdir)
  if metrics is not None and metrics.get("steps") == steps:
    logging.info("skip %s: metrics.json already has %d steps", workdir,
                 steps)
    return metrics, None
  os.makedirs(workdir, exist_ok=True)
  cmd = ([sys.executable, TRAIN_SCRIPT, f"--scene={scene_dir}",
          f"--workdir={workdir}", f"--steps={steps}", "--resume"]
         + common + extra)
  env = dict(os.environ)
  # The checkout, not a stale installed copy of clipgs_jax.
  env["PYTHONPATH"] = os.pathsep.join(
      [REPO_ROOT] + [p for p in [env.get("PYTHONPATH")] if p])
  log_path = os.path.join(workdir, "train.log")
  logging.info("run %s > %s", shlex.join(cmd), log_path)
  with open(log_path, "a") as log:
    log.write(f"\n# {datetime.datetime.now().isoformat()}: "
              f"{shlex.join(cmd)}\n")
    log.flush()
    code = subprocess.call(cmd, cwd=REPO_ROOT, env=env, stdout=log,
                           stderr=subprocess.STDOUT)
  if code != 0:
    logging.error("row %s failed with exit code %d; last lines of %s:\n%s",
                  workdir, code, log_path, _log_tail(log_path))
    return None, f"exit code {code}"
  metrics = read_metrics(workdir)
  if metrics is None:
    return None, "no metrics.json"
  if metrics.get("steps") != steps:
    # --resume from a longer run's checkpoint: say so, not a wrong row.
    return None, (f"metrics.json has {metrics.get('steps')} steps, wanted "
                  f"{steps} (stale workdir?)")
  return metrics, None


def run_table(benchmarks: list[str], workroot: str, steps: int, *,
              downscale: int = 1, seed: int = 0, tau: float | None = None,
              weighting: str = "visibility", lpips_net: str = "alex",
              clip_weights: str | None = None, extra_flags: str = "",
              out: str | None = None,
              only_rows: list[str] | None = None) -> list[dict]:
  """Runs every row of every benchmark and writes table.md / table.json.

  Returns:
    list of row dicts, as in table.json.
  """
  names = [scene_name(b) for b in benchmarks]
  if len(set(names)) != len(names):
    raise ValueError(f"benchmark basenames must differ, got {names}.")
  common = common_flags(downscale, seed, lpips_net)
  extra = shlex.split(extra_flags)
  rows = []
  for bench, name in zip(benchmarks, names):
    for row in row_names(clip_weights, only_rows):
      workdir = os.path.join(workroot, name, row)
      flags_ = row_flags(row, tau=tau, weighting=weighting,
                         clip_weights=clip_weights)
      metrics, error = run_row(os.path.abspath(bench), workdir, steps,
                               common + flags_, extra)
      r = collect_row(name, row, metrics, error)
      if error:
        r["log_tail"] = _log_tail(os.path.join(workdir, "train.log"))
      rows.append(r)
  rows = add_deltas(rows)
  settings = {
      "steps": steps, "downscale": downscale, "seed": seed,
      "tau": tau if tau is not None else "train.py default",
      "semantic_weighting": weighting, "lpips_net": lpips_net,
      "extra_flags": extra_flags or "(none)",
      "clip_weights": clip_weights or "(none: no clip row)",
      **machine_and_date(),
  }
  out = out or workroot
  os.makedirs(out, exist_ok=True)
  fileio.write_json(os.path.join(out, "table.json"),
                    {"settings": settings, "rows": rows})
  text = format_markdown(rows, settings)
  write_text(os.path.join(out, "table.md"), text)
  logging.info("wrote %s\n%s", os.path.join(out, "table.md"), text)
  return rows


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  if FLAGS.steps <= 0:
    raise app.UsageError(f"--steps must be positive, got {FLAGS.steps}.")
  for b in FLAGS.benchmarks:
    if not os.path.isdir(b):
      raise app.UsageError(f"benchmark {b} is not a folder.")
  rows = run_table(
      FLAGS.benchmarks, os.path.abspath(FLAGS.workroot), FLAGS.steps,
      downscale=FLAGS.downscale, seed=FLAGS.seed, tau=FLAGS.tau,
      weighting=FLAGS.semantic_weighting, lpips_net=FLAGS.lpips_net,
      clip_weights=FLAGS.clip_weights, extra_flags=FLAGS.extra_flags,
      out=FLAGS.out, only_rows=FLAGS.rows)
  with open(os.path.join(FLAGS.out or FLAGS.workroot, "table.md")) as f:
    print(f.read())
  failed = [f"{r['scene']}/{r['row']}" for r in rows if r["status"] != "ok"]
  if failed:
    logging.error("failed rows: %s", ", ".join(failed))
    sys.exit(1)


if __name__ == "__main__":
  _define_flags()
  cli.run(main)
