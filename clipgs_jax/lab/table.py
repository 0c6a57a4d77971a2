"""Benchmark and ablation tables from finished runs' metrics.json dicts.

Also what every sweep output shares (sweep.py, tau_sweep.py, figures.py):
the table's row names (ROWS, LABELS, VANILLA, CLEAN), RowResult,
collect_row, by_scene, test_psnr, fmt, write_outputs and machine_and_date.
"""

import datetime
import math
import os
import platform
from typing import NamedTuple

from clipgs_jax import config as config_lib
from clipgs_jax import fileio
from clipgs_jax import run as run_lib

# Rows that the others are measured against (by name, in every sweep).
VANILLA, CLEAN = "vanilla", "clean"
# The benchmark table's rows in table order (configs/table.py says what each
# runs), with the short names that figures give them.
LABELS = {
    VANILLA: "vanilla 3DGS",
    "oracle": "CLIP-GS (ORACLE scorer)",
    "oracle_pixel": "localized (ORACLE-PIXEL)",
    "oracle_pixel_masked": "localized + loss masking (ORACLE-PIXEL)",
    "clip": "CLIP-GS (CLIP)",
    "clip_pixel": "localized (dense CLIP)",
    "residual": "residual map (photos only)",
    "residual_features": "residual map + feature regions (photos only)",
    "residual_features_remember":
        "residual map + feature regions, remembered (photos only)",
    "learned": "learned map, SLS-mlp on AlexNet features (photos only)",
    "oracle_patch_residual": "residual map gated by ORACLE-PATCH",
    "clip_residual": "residual map gated by dense CLIP",
    CLEAN: "clean upper bound",
    "residual_clean": "residual map on the clean views (control)",
    "residual_features_clean":
        "residual map + feature regions on the clean views (control)",
    "residual_features_remember_clean":
        "residual map + feature regions, remembered, on the clean views "
        "(control)",
    "learned_clean": "learned map on the clean views (control)",
}
ROWS = tuple(LABELS)
# Why an ablation row without CLIP weights did not run.
NEEDS_CLIP = "needs --clip_weights (the oracle ignores prompts)"


class RowResult(NamedTuple):
  """One row of a sweep after it ran (or was skipped)."""
  scene: str                # the benchmark's name ("" for the demo)
  row: str                  # the row's name (configs/*.py)
  tau: float | None         # tau sweeps: the row's tau
  cfg: config_lib.Config    # the row's config
  metrics: dict | None      # metrics.json; None: failed or not run
  error: str | None         # the failure's one line; None with metrics None:
  #                           not run (a clip row without weights)
  workdir: str              # the row's run folder


def row_label(cfg: config_lib.Config) -> str:
  """How a table names a row's run before (or without) its metrics."""
  if cfg.semantic.enabled:
    return run_lib.semantic_label(cfg)
  if cfg.data.train_split == "clean":
    return "3DGS on clean views (upper bound)"
  return "vanilla 3DGS (clutter)"


def finite(x) -> float | None:
  """x as a float, None for missing or non-finite values (JSON-safe)."""
  if x is None:
    return None
  x = float(x)
  return x if math.isfinite(x) else None


def collect_row(scene: str, row: str, cfg: config_lib.Config,
                metrics: dict | None, error: str | None = None) -> dict:
  """One table row from a run's metrics.json dict (None: the run failed).

  Args:
    scene: str, the benchmark name.
    row: str, the row's name (configs/table.py).
    cfg: the row's Config (guided or not, its label).
    metrics: dict, the run's metrics.json, or None.
    error: str, why the row failed, or None.

  Returns:
    dict with "scene", "row", "method", "guided", "status" ("ok" or
    "failed"), "error", "psnr", "ssim", "lpips", "lpips_net",
    "train_seconds", "num_gaussians", "steps", "fraction_pruned",
    "mask_iou" (the pruned Gaussians' rendered alpha against the transient
    masks; None for unguided rows and runs that pruned nothing),
    "clean_views" (the row trained on the clean twins) and
    "map_precision", "map_recall", "map_iou" (pixel evidence: the maps the
    loss used at the last curve point against the ground-truth masks;
    evaluation.mask_quality); numbers are None where unknown or
    non-finite.
  """
  guided = cfg.semantic.enabled
  out = {"scene": scene, "row": row, "method": row_label(cfg),
         "guided": guided,
         "status": "failed" if (error or metrics is None) else "ok",
         "error": error or (None if metrics is not None else "no metrics"),
         "psnr": None, "ssim": None, "lpips": None, "lpips_net": None,
         "train_seconds": None, "num_gaussians": None, "steps": None,
         "fraction_pruned": None, "mask_iou": None,
         "clean_views": cfg.data.train_split == "clean",
         "map_precision": None, "map_recall": None, "map_iou": None}
  if metrics is None:
    return out
  test = metrics.get("test", {})
  semantic = metrics.get("semantic")
  if guided and semantic and semantic.get("label"):
    out["method"] = semantic["label"]
  if cfg.semantic.scorer == "oracle" and "ORACLE" not in out["method"]:
    # The oracle reads ground-truth masks; the table must never let it pass
    # for CLIP.
    out["method"] = "ORACLE: " + out["method"]
  out.update(
      psnr=finite(test.get("psnr")), ssim=finite(test.get("ssim")),
      lpips=finite(test.get("lpips")), lpips_net=test.get("lpips_net"),
      train_seconds=finite(metrics.get("train_seconds")),
      num_gaussians=metrics.get("num_gaussians"),
      steps=metrics.get("steps"))
  if guided and semantic:
    out["fraction_pruned"] = finite(semantic.get("fraction_pruned"))
    iou = semantic.get("pruned_mask_iou") or {}
    if iou.get("num_gaussians") != 0:  # 0: nothing pruned, no IoU to give
      out["mask_iou"] = finite(iou.get("mean"))
    quality = semantic.get("mask_quality") or {}
    out.update(map_precision=finite(quality.get("precision")),
               map_recall=finite(quality.get("recall")),
               map_iou=finite(quality.get("iou")))
  return out


def add_deltas(rows: list[dict]) -> list[dict]:
  """Adds "delta_psnr" (guided minus vanilla) and "gap_to_clean".

  gap_to_clean is clean PSNR minus the row's PSNR (dB; positive: below the
  upper bound), for every row but clean. A guided row trained on the clean
  views (a control) is measured against clean, not vanilla: its delta is
  what its map costs where there is nothing to remove. Either is None
  where a PSNR is missing or the row does not get one. Returns new dicts.
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
      vanilla = psnr_of(r["scene"], VANILLA)
      clean = psnr_of(r["scene"], CLEAN)
      base = clean if r.get("clean_views") else vanilla
      if r["guided"] and base is not None:
        r["delta_psnr"] = r["psnr"] - base
      if r["row"] != CLEAN and clean is not None:
        r["gap_to_clean"] = clean - r["psnr"]
    out.append(r)
  return out


def fmt(x, spec: str, missing: str = "n/a") -> str:
  """`x` formatted with `spec`, or `missing` for None."""
  return missing if x is None else format(x, spec)


def _settings_lines(title: str, settings: dict) -> list[str]:
  return [f"# {title}", ""] + [f"- {k}: {v}" for k, v in settings.items()]


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
  lines = _settings_lines("CLIP-GS benchmark table", settings)
  lines += [
      "", "Every row: the same config but for its overrides. "
      "ΔPSNR: guided minus vanilla 3DGS on the same scene (a control row "
      "on the clean views: minus the clean row); gap to clean: clean upper "
      "bound minus the row (dB). ORACLE rows read ground-truth masks, not "
      "CLIP. Fraction pruned: by eq. 13, both its score and its visibility "
      "condition. Pruned IoU: the rendered alpha (> 0.5) of the Gaussians "
      "the score condition pruned against the training views' transient "
      "masks. Map P / R / IoU: the per-pixel maps the loss used at the end "
      "(> 0.5) against the ground-truth masks, over all training views.",
      "",
      f"| scene | method | PSNR | SSIM | LPIPS ({net}) | train s | "
      "Gaussians | fraction pruned | pruned IoU | map P / R / IoU | ΔPSNR "
      "| gap to clean |",
      "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
  for r in rows:
    if r["status"] != "ok":
      cells = [r["scene"], r["method"],
               f"FAILED ({r['error']})"] + ["—"] * 9
    else:
      guided = r["guided"]
      cells = [
          r["scene"], r["method"], fmt(r["psnr"], ".2f"),
          fmt(r["ssim"], ".4f"), fmt(r["lpips"], ".4f"),
          fmt(r["train_seconds"], ".1f"),
          fmt(r["num_gaussians"], "d"),
          fmt(r["fraction_pruned"], ".3f") if guided else "—",
          fmt(r.get("mask_iou"), ".3f") if guided else "—",
          " / ".join(fmt(r.get(k), ".2f") for k in (
              "map_precision", "map_recall", "map_iou"))
          if r.get("map_iou") is not None else "—",
          fmt(r["delta_psnr"], "+.2f") if guided else "—",
          fmt(r["gap_to_clean"], "+.2f") if r["row"] != CLEAN else "—"]
    lines.append("| " + " | ".join(c.replace("|", "/") for c in cells)
                 + " |")
  return "\n".join(lines) + "\n"


def ablation_row(row: str, description: str, cfg: config_lib.Config,
                 metrics: dict | None, error: str | None,
                 vanilla_psnr: float | None, clean_psnr: float | None
                 ) -> dict:
  """One ablation row; metrics None with error None means "not run"."""
  if metrics is None and error is None:
    return {"row": row, "method": description, "status": "not run",
            "error": NEEDS_CLIP}
  r = collect_row("", row, cfg, metrics, error)
  r.update(method=description)
  ok = r["psnr"] is not None
  r["delta_psnr"] = (r["psnr"] - vanilla_psnr if ok and row != VANILLA
                     and vanilla_psnr is not None else None)
  r["gap_to_clean"] = (clean_psnr - r["psnr"] if ok and row != CLEAN
                       and clean_psnr is not None else None)
  return r


def format_ablation(rows: list[dict], settings: dict) -> str:
  """ablate.md: the settings, then one Markdown row per ablation row."""
  nets = sorted({r.get("lpips_net") for r in rows if r.get("lpips_net")})
  lines = _settings_lines("CLIP-GS ablation", settings)
  lines += ["", "ΔPSNR: the row minus vanilla; gap: clean minus the row "
            "(dB). ORACLE rows score views with ground-truth masks.", "",
            f"| row | PSNR | ΔPSNR | gap to clean | SSIM | LPIPS "
            f"({', '.join(nets) or '?'}) | Gaussians | fraction pruned |",
            "|---|---:|---:|---:|---:|---:|---:|---:|"]
  for r in rows:
    if r["status"] != "ok":
      lines.append(f"| {r['method']} | {r['status']}: {r['error']} |"
                   + " — |" * 6)
      continue
    lines.append(
        f"| {r['method']} | {fmt(r['psnr'], '.2f')} | "
        f"{fmt(r['delta_psnr'], '+.2f', '—')} | "
        f"{fmt(r['gap_to_clean'], '+.2f', '—')} | {fmt(r['ssim'], '.4f')} | "
        f"{fmt(r['lpips'], '.4f')} | "
        f"{fmt(r['num_gaussians'], 'd')} | "
        f"{fmt(r['fraction_pruned'], '.3f', '—')} |")
  return "\n".join(lines) + "\n"


def machine_and_date() -> dict:
  """The "machine" and "date" settings every benchmark output names."""
  return {"machine": f"{platform.node()}, {os.cpu_count()} cpus",
          "date": datetime.datetime.now().isoformat(timespec="seconds")}


def write_outputs(folder: str, stem: str, settings: dict, rows: list[dict],
                  text: str) -> None:
  """folder/stem.json ({"settings", "rows"}) and folder/stem.md, atomically.
  """
  os.makedirs(folder, exist_ok=True)
  fileio.write_json(os.path.join(folder, stem + ".json"),
                        {"settings": settings, "rows": rows})

  def write(tmp):
    with open(tmp, "w") as f:
      f.write(text)
  fileio.atomic_write(os.path.join(folder, stem + ".md"), write, ".md")


def by_scene(results: list[RowResult]) -> dict[str, list[RowResult]]:
  """The results grouped by benchmark, in order."""
  grouped = {}
  for result in results:
    grouped.setdefault(result.scene, []).append(result)
  return grouped


def test_psnr(metrics: dict | None) -> float | None:
  """metrics.json's test PSNR, None when there is none."""
  return ((metrics or {}).get("test") or {}).get("psnr")


def write_table(results: list[RowResult], settings: dict, out: str,
                sweep: dict) -> dict:
  """table.md / table.json in `out`; clip rows that did not run are left
  out. Returns table.json's dict."""
  del sweep
  rows = [collect_row(r.scene, r.row, r.cfg, r.metrics, r.error)
          for r in results if r.metrics is not None or r.error is not None]
  rows = add_deltas(rows)
  write_outputs(out, "table", settings, rows,
                format_markdown(rows, settings))
  return {"settings": settings, "rows": rows}


def write_ablation(results: list[RowResult], settings: dict, out: str,
                   sweep: dict) -> dict:
  """out/<benchmark>/ablate.md / .json; sweep["descriptions"] names the
  rows. Returns {"settings", "rows"} over every benchmark."""
  every = []
  for name, group in by_scene(results).items():
    psnr = {r.row: test_psnr(r.metrics) for r in group}
    rows = [ablation_row(r.row, sweep["descriptions"].get(r.row, r.row),
                         r.cfg, r.metrics, r.error, psnr.get(VANILLA),
                         psnr.get(CLEAN)) for r in group]
    s = dict(settings, benchmark=name)
    write_outputs(os.path.join(out, name), "ablate", s, rows,
                  format_ablation(rows, s))
    every += rows
  return {"settings": settings, "rows": every}
