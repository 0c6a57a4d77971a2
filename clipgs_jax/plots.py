"""Error-against-run-time plots: test MSE (log) against training seconds."""

import json
import os

# matplotlib.figure, not pyplot: figures that only go to files need no
# backend, and importing the library never changes the backend of the
# user's session (a notebook keeps its inline plots).
from matplotlib import figure

from clipgs_jax import fileio


def _read(path: str) -> list[dict]:
  with open(path) as f:
    curve = json.load(f)
  if not isinstance(curve, list) or not all(
      {"step", "seconds", "test_psnr"} <= set(p) for p in curve):
    raise ValueError(f"plots: {path} is not a list of {{step, seconds, "
                     "test_psnr}} points; pass a curve.json from train.py.")
  return curve


def save_figure(fig, out_path: str) -> None:
  """Lays out `fig` and writes it as a PNG atomically."""
  fig.tight_layout()
  fileio.atomic_write(out_path, fig.savefig, ".png")


def plot(curve_paths: list[str], out_path: str,
         labels: list[str] | None = None, x: str = "seconds") -> None:
  """Writes the error-against-time plot of the given curves, atomically."""
  if labels is not None and len(labels) != len(curve_paths):
    raise ValueError(f"plots: {len(labels)} labels for "
                     f"{len(curve_paths)} curves.")
  fig = figure.Figure(figsize=(6, 4), dpi=120)
  draw_curves(fig.subplots(), {
      (labels[i] if labels else
       os.path.basename(os.path.dirname(os.path.abspath(path)))): _read(path)
      for i, path in enumerate(curve_paths)}, x)
  save_figure(fig, out_path)


def draw_curves(ax, curves: dict[str, list[dict]], x: str = "seconds"
                ) -> None:
  """Test MSE (log) of each {label: [{step, seconds, test_psnr}]} curve
  against `x` ("seconds" or "step") on `ax`, the last PSNR written by it."""
  for label, curve in curves.items():
    xs = [p[x] for p in curve]
    mse = [10 ** (-p["test_psnr"] / 10) for p in curve]
    ax.plot(xs, mse, marker="o", markersize=3, label=label)
    if curve:
      ax.annotate(f"{curve[-1]['test_psnr']:.2f} dB", (xs[-1], mse[-1]),
                  textcoords="offset points", xytext=(4, 4), fontsize=8)
  ax.set_yscale("log")
  ax.set_xlabel("training time (s, evaluation excluded)" if x == "seconds"
                else "step")
  ax.set_ylabel("test MSE = 10^(-PSNR/10)")
  ax.grid(True, which="both", alpha=0.3)
  ax.legend(fontsize=8)


def side_by_side(images, titles: list[str], out_path: str,
                 scale: int = 3) -> None:
  """Writes float [H, W, 3] images in one row with a title each (PNG).

  Pixels are repeated `scale` times (nearest), so small renders stay sharp.
  """
  if len(images) != len(titles):
    raise ValueError(f"plots.side_by_side: {len(images)} images for "
                     f"{len(titles)} titles.")
  height, width = images[0].shape[:2]
  fig = figure.Figure(dpi=100, figsize=(
      len(images) * width * scale / 100, height * scale / 100 + 0.5))
  axes = fig.subplots(1, len(images), squeeze=False)[0]
  for ax, image, title in zip(axes, images, titles):
    ax.imshow(image.clip(0.0, 1.0), interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.axis("off")
  save_figure(fig, out_path)
