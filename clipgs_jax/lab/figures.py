"""Paper figures from a benchmark table's runs: render grids, curves."""

import json
import os

from absl import logging
from matplotlib import figure
import numpy as np

from clipgs_jax import camera
from clipgs_jax import plots
from clipgs_jax import run as run_lib
from clipgs_jax.data import images
from clipgs_jax.lab import table
from clipgs_jax.data import scene as scene_lib

INPUT_TITLE = "input (nearest training view, with transients)"
PANEL_INCHES = 2.4


def nearest_train_view(centre, train_cams) -> int:
  """Index of the training camera whose centre is nearest `centre`.

  Args:
    centre: float [3], a camera centre in world coordinates
      (camera.camera_center).
    train_cams: camera.Camera with a leading [V] axis (Views.cameras).

  Returns:
    int in [0, V).
  """
  dist = np.linalg.norm(camera.camera_center(train_cams) - centre, axis=-1)
  return int(np.argmin(dist))


def view_psnr(a: np.ndarray, b: np.ndarray) -> float:
  """PSNR in dB (peak 1) of two images of one shape; inf when equal."""
  a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
  if a.shape != b.shape:
    raise ValueError(f"view_psnr: shapes differ, {a.shape} vs {b.shape}.")
  mse = float(np.mean(np.square(a - b)))
  return float("inf") if mse == 0 else -10.0 * float(np.log10(mse))


def pick_views(num_views: int, count: int) -> list[int]:
  """`count` indices evenly spaced over range(num_views), first and last."""
  if count < 1:
    raise ValueError(f"views must be positive, got {count}.")
  count = min(count, num_views)
  return sorted({int(round(x))
                 for x in np.linspace(0, num_views - 1, count)})


def present_rows(scene_runs: str) -> list[str]:
  """The table.ROWS with a folder in scene_runs; ValueError when none."""
  rows = [r for r in table.ROWS if os.path.isdir(os.path.join(scene_runs, r))]
  if not rows:
    raise ValueError(f"figures: no row folder ({', '.join(table.ROWS)}) in "
                     f"{scene_runs}; run the table first or fix "
                     "--runs.")
  for r in table.ROWS:
    if r not in rows and r != "clip":
      logging.warning("figures: %s is missing; no %s column or curve.",
                      os.path.join(scene_runs, r), r)
  return rows


def runs_downscale(scene_runs: str, rows: list[str]) -> int:
  """The downscale of the rows' run.json files; they must agree."""
  found = {}
  for r in rows:
    try:
      with open(os.path.join(scene_runs, r, run_lib.RUN_JSON)) as f:
        found[r] = int(json.load(f)["downscale"])
    except (OSError, ValueError, KeyError, TypeError):
      logging.warning("figures: no downscale in %s/%s/run.json", scene_runs,
                      r)
  if not found:
    raise ValueError(f"figures: no run.json with a downscale in the rows of "
                     f"{scene_runs}; pass --figure_downscale.")
  if len(set(found.values())) > 1:
    raise ValueError(f"figures: the rows of {scene_runs} differ in "
                     f"downscale {found}; their renders are not comparable.")
  return next(iter(found.values()))


def _panel(ax, image, title, xlabel=None):
  ax.imshow(np.clip(image, 0, 1), interpolation="nearest")
  ax.set_title(title, fontsize=7)
  if xlabel:
    ax.set_xlabel(xlabel, fontsize=8)
  ax.set_xticks([])
  ax.set_yticks([])


def make_grid(bench: str, scene_runs: str, out_path: str, views: int = 3,
              downscale: int | None = None) -> dict:
  """Writes the render grid of one benchmark, atomically.

  Args:
    bench: str, the benchmark scene folder.
    scene_runs: str, <table root>/<scene>, holding the row folders.
    out_path: str, the PNG to write.
    views: int, number of test views (grid rows).
    downscale: int or None, image downscale (None: the rows' run.json).

  Returns:
    dict with "rows" (the render columns drawn, in order), "titles" (all
    column titles) and "views": per grid row {"test", "input", "psnr":
    {row: dB}}.
  """
  rows = present_rows(scene_runs)
  downscale = downscale or runs_downscale(scene_runs, rows)
  scene = scene_lib.load_scene(bench, downscale=downscale,
                               train_split="clutter")
  test, train = scene.test, scene.train
  order = np.argsort(test.names)
  picked = [int(order[i]) for i in pick_views(len(order), views)]
  renders = {r: {} for r in rows}
  for r in rows:
    for i in picked:
      stem = os.path.splitext(os.path.basename(test.names[i]))[0]
      path = os.path.join(scene_runs, r, run_lib.TEST_RENDERS,
                          stem + ".png")
      if not os.path.isfile(path):
        logging.warning("figures: render %s is missing; %s column left out.",
                        path, r)
        renders[r] = None
        break
      image = images.read_image(path)
      if image.shape != test.images[i].shape:
        raise ValueError(
            f"figures: {path} is {image.shape[1]}x{image.shape[0]} but the "
            f"test view at downscale {downscale} is {test.images[i].shape[1]}"
            f"x{test.images[i].shape[0]}; pass the runs' downscale as "
            "--figure_downscale.")
      renders[r][i] = image
  cols = [r for r in rows if renders[r] is not None]
  titles = [INPUT_TITLE] + [table.LABELS[r] for r in cols] + ["ground truth"]
  test_centres = camera.camera_center(test.cameras)   # [V, 3]
  h, w = test.images.shape[1:3]
  fig = figure.Figure(dpi=150, figsize=(
      PANEL_INCHES * len(titles), (PANEL_INCHES * h / w + 0.6) * len(picked)))
  axes = fig.subplots(len(picked), len(titles), squeeze=False)
  summary = {"rows": cols, "titles": titles, "views": []}
  for k, i in enumerate(picked):
    gt = test.images[i]
    j = nearest_train_view(test_centres[i], train.cameras)
    head = (lambda t: t + "\n") if k == 0 else (lambda t: "")
    _panel(axes[k, 0], train.images[j], head(INPUT_TITLE) + train.names[j])
    view = {"test": test.names[i], "input": train.names[j], "psnr": {}}
    for c, r in enumerate(cols, 1):
      view["psnr"][r] = view_psnr(renders[r][i], gt)
      _panel(axes[k, c], renders[r][i], head(table.LABELS[r]).rstrip(),
             f"PSNR {view['psnr'][r]:.2f} dB")
    _panel(axes[k, -1], gt, head("ground truth") + test.names[i])
    summary["views"].append(view)
  plots.save_figure(fig, out_path)
  logging.info("figures: wrote %s", out_path)
  return summary


def make_curve(scene_runs: str, out_path: str) -> list[str]:
  """Writes the error-against-time plot of the rows with a curve.json.

  Returns:
    list of the rows plotted (empty, and no file written, when none has a
    curve.json).
  """
  rows, paths = [], []
  for r in present_rows(scene_runs):
    path = os.path.join(scene_runs, r, run_lib.CURVE_JSON)
    if os.path.isfile(path):
      rows.append(r)
      paths.append(path)
    else:
      logging.warning("figures: %s is missing; no %s curve.", path, r)
  if not rows:
    logging.warning("figures: no curve.json in %s; no curve plot.",
                    scene_runs)
    return []
  plots.plot(paths, out_path, [table.LABELS[r] for r in rows])
  logging.info("figures: wrote %s", out_path)
  return rows


def make_figures(benchmarks: list[str], workroot: str, out: str,
                 views: int = 3, downscale: int | None = None) -> list[str]:
  """Grid and curve PNGs of every benchmark; returns the paths written."""
  for bench in benchmarks:
    if not os.path.isdir(bench):
      raise FileNotFoundError(f"benchmark {bench} is not a folder; pass "
                              "the scene folders the table ran on.")
  written = []
  for bench in benchmarks:
    name = os.path.basename(os.path.normpath(bench))
    scene_runs = os.path.join(workroot, name)
    grid = os.path.join(out, f"{name}_grid.png")
    make_grid(bench, scene_runs, grid, views, downscale)
    written.append(grid)
    curve = os.path.join(out, f"{name}_curve.png")
    if make_curve(scene_runs, curve):
      written.append(curve)
  return written
