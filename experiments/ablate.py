"""Ablations of CLIP-GS guidance: which part helps, and do the prompts matter.

  python experiments/ablate.py --benchmark=DIR --workroot=DIR --steps=N
      [--downscale=K] [--seed=S] [--tau=T]
      [--semantic_weighting=visibility|contribution] [--lpips_net=alex|vgg]
      [--clip_weights=PATH] [--extra_flags="--tile_budget=8192 ..."]
      [--out=DIR]

Rows, each one experiments/train.py run into workroot/<scene>/<row>/ with
the settings of experiments/table.py (whose vanilla, oracle, clip and clean
rows are the same folders, so runs are shared and resumable):
  vanilla            3DGS on the clutter views (reference)
  oracle             ORACLE scorer, opacity loss and pruning (the table's)
  oracle_reg_only    ... opacity loss only (--nosemantic_prune)
  oracle_prune_only  ... pruning only (--lambda_c=0)
  clip               CLIP scorer, the paper's distractor prompts
  clip_generic       CLIP scorer, generic prompts ("a photo of an object",
                     "a photo of a thing")
  clean              3DGS on the clean views (upper bound)
The oracle scores views from ground-truth masks and ignores prompts, so the
prompt rows need --clip_weights; without it they are listed as not run.

Writes ablate.md and ablate.json into --out (default workroot/<scene>).
"""

import os
import shlex

from absl import app
from absl import flags

from clipgs_jax import cli
from clipgs_jax import fileio
import table  # pylint: disable=g-import-not-at-top

FLAGS = flags.FLAGS
GENERIC_PROMPTS = ("a photo of an object", "a photo of a thing")
# row -> (table row it derives from, extra train.py flags, description)
ROWS = {
    "vanilla": ("vanilla", [], "vanilla 3DGS (clutter)"),
    "oracle": ("oracle", [], "ORACLE: opacity loss + pruning"),
    "oracle_reg_only": ("oracle", ["--nosemantic_prune"],
                        "ORACLE: opacity loss only"),
    "oracle_prune_only": ("oracle", ["--lambda_c=0"],
                          "ORACLE: pruning only"),
    "clip": ("clip", [], "CLIP: paper prompts"),
    "clip_generic": ("clip", ["--distractor_prompts="
                              + ",".join(GENERIC_PROMPTS)],
                     "CLIP: generic prompts"),
    "clean": ("clean", [], "3DGS on clean views (upper bound)"),
}
NEEDS_CLIP = "needs --clip_weights (the oracle ignores prompts)"


def _define_flags() -> None:
  table.define_run_flags()
  flags.DEFINE_string("benchmark", None, "Benchmark scene folder.")
  flags.DEFINE_float("tau", None, "Prune threshold (default: train.py's).")
  flags.DEFINE_string("clip_weights", None, "CLIP weights: adds the prompt "
                      "rows.")
  flags.DEFINE_string("out", None, "Output folder (default "
                      "workroot/<scene>).")
  flags.mark_flags_as_required(["benchmark"])


def row_flags(name: str, *, tau: float | None, weighting: str,
              clip_weights: str | None) -> list[str] | None:
  """train.py flags of ablation row `name`; None when it cannot run."""
  base, extra, _ = ROWS[name]
  if base == "clip" and not clip_weights:
    return None
  return table.row_flags(base, tau=tau, weighting=weighting,
                         clip_weights=clip_weights) + extra


def ablation_row(name: str, metrics: dict | None, error: str | None,
                 vanilla_psnr: float | None, clean_psnr: float | None
                 ) -> dict:
  """One ablation row; metrics None with error None means "not run"."""
  base, _, description = ROWS[name]
  if metrics is None and error is None:
    return {"row": name, "method": description, "status": "not run",
            "error": NEEDS_CLIP}
  r = table.collect_row("", base, metrics, error)
  r.update(row=name, method=description)
  ok = r["psnr"] is not None
  r["delta_psnr"] = (r["psnr"] - vanilla_psnr if ok and name != "vanilla"
                     and vanilla_psnr is not None else None)
  r["gap_to_clean"] = (clean_psnr - r["psnr"] if ok and name != "clean"
                       and clean_psnr is not None else None)
  return r


def format_markdown(rows: list[dict], settings: dict) -> str:
  fmt = table._fmt  # pylint: disable=protected-access
  nets = sorted({r.get("lpips_net") for r in rows if r.get("lpips_net")})
  lines = ["# CLIP-GS ablation", ""]
  lines += [f"- {k}: {v}" for k, v in settings.items()]
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


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  if not os.path.isdir(FLAGS.benchmark):
    raise app.UsageError(f"--benchmark={FLAGS.benchmark} is not a folder.")
  scene = table.scene_name(FLAGS.benchmark)
  root = os.path.join(os.path.abspath(FLAGS.workroot), scene)
  bench = os.path.abspath(FLAGS.benchmark)
  common = table.common_flags(FLAGS.downscale, FLAGS.seed, FLAGS.lpips_net)
  extra = shlex.split(FLAGS.extra_flags)
  results = {}
  for name in ROWS:
    flags_ = row_flags(name, tau=FLAGS.tau,
                       weighting=FLAGS.semantic_weighting,
                       clip_weights=FLAGS.clip_weights)
    results[name] = ((None, None) if flags_ is None else table.run_row(
        bench, os.path.join(root, name), FLAGS.steps, common + flags_,
        extra))
  psnr = lambda name: ((results[name][0] or {}).get("test", {})
                       .get("psnr"))
  rows = [ablation_row(name, *results[name], psnr("vanilla"), psnr("clean"))
          for name in ROWS]
  settings = {
      "benchmark": scene, "steps": FLAGS.steps,
      "downscale": FLAGS.downscale, "seed": FLAGS.seed,
      "tau": FLAGS.tau if FLAGS.tau is not None else "train.py default",
      "semantic_weighting": FLAGS.semantic_weighting,
      "extra_flags": FLAGS.extra_flags or "(none)",
      "clip_weights": FLAGS.clip_weights or "(none: prompt rows not run)",
      **table.machine_and_date()}
  out = FLAGS.out or root
  os.makedirs(out, exist_ok=True)
  fileio.write_json(os.path.join(out, "ablate.json"),
                    {"settings": settings, "rows": rows})
  text = format_markdown(rows, settings)
  table.write_text(os.path.join(out, "ablate.md"), text)
  print(text)


if __name__ == "__main__":
  _define_flags()
  cli.run(main)
