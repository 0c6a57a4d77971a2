"""What to do with finished run folders: metrics, renders, curves, figures.

  python experiments/report.py --report=metrics --runs=DIR
      [--gaussians=auto|checkpoint|ply] [--lpips_backbone=alex|vgg]
      [--dry_run]
  python experiments/report.py --report=renders --runs=DIR
  python experiments/report.py --report=masks --runs=DIR [--mask_tau=T]
  python experiments/report.py --report=evidence --runs=DIR
  python experiments/report.py --report=loss_maps --runs=DIR [--views=3]
      [--clean_run=CLEAN_DIR]
  python experiments/report.py --report=map_limits --runs=DIR
  python experiments/report.py --report=curve --runs=DIR1,DIR2
      --curve_png=curve.png [--labels=a,b] [--x_axis=seconds|step]
  python experiments/report.py --report=seeds --runs=ROOT_S0,ROOT_S1,...
      [--set_apart=VIEW[,VIEW...]]
  python experiments/report.py --report=figures --runs=TABLE_ROOT
      --benchmarks=DIR[,DIR...] --figures_dir=DIR [--views=3]
      [--figure_downscale=K]

metrics: renders every test view of the run again (the checkpoint, or the
  PLY when there is none or --gaussians=ply) and replaces the "test" block
  of metrics.json unless --dry_run; prints new and stored numbers.
renders: the colour of every training view, DIR/renders/train/<stem>.png.
masks: the alpha of the alive Gaussians with s_j > tau (tau: the run's
  semantic.tau unless --mask_tau) as grey DIR/renders/masks/<stem>.png;
  with ground-truth masks, their IoU goes into metrics.json "mask_iou".
evidence: on a persistent benchmark, the ground-truth pixel evidence s_j
  of the Gaussians on billboards (ghosts, by geometry) against the rest,
  raw and agreement-weighted: DIR/evidence.json and DIR/evidence.png
  (clipgs_jax/lab/ghost_evidence.py).
loss_maps: with pixel evidence, the map m of every training view with
  the final model against the ground truth, and the worst views:
  DIR/loss_maps.json and .png (clipgs_jax/lab/loss_maps.py); a residual
  map's recall after each of its steps; with --clean_run (the clean twin's
  run), how many transient pixels differ from what lies behind them.
map_limits: on a benchmark run, what a map could reach with the truth:
  the learned classifier fitted to the true masks, multi-view photo
  consistency on the run's geometry, the bare residual test, and for a
  remembered run its memory less a multi-view release
  (clipgs_jax/lab/map_limits.py): DIR/map_limits.json.
curve: test MSE (log) against training time of each run's curve.json (a
  run folder or the curve.json itself).
seeds: the table roots of several seeds as one table: every cell's PSNR
  per seed, its mean and its difference from vanilla (clean for a control
  row) paired by seed; the test views that move most between seeds, and
  --set_apart views apart (clipgs_jax/lab/seeds.py).
figures: per benchmark, a render grid and error curves of the table's
  runs in TABLE_ROOT/<benchmark name>/<row>/ (clipgs_jax/lab/figures.py).
"""

import os

from absl import flags

from clipgs_jax import cli
from clipgs_jax import evaluation
from clipgs_jax.lab import ghost_evidence
from clipgs_jax.lab import figures
from clipgs_jax.lab import loss_maps
from clipgs_jax.lab import map_limits
from clipgs_jax import plots
from clipgs_jax.lab import report
from clipgs_jax.lab import seeds
from clipgs_jax import run as run_lib

_REPORT = flags.DEFINE_enum(
    "report", None,
    ["metrics", "renders", "masks", "evidence", "loss_maps", "map_limits",
     "curve", "seeds", "figures"],
    "What to make of the runs.")
_RUNS = flags.DEFINE_list("runs", None, "Run folders written by "
                          "experiments/train.py (figures: the table's root; "
                          "seeds: the tables' roots).")
_GAUSSIANS = flags.DEFINE_enum("gaussians", "auto", list(report.SOURCES),
                               "metrics: where the Gaussians come from "
                               "(auto: the checkpoint if present).")
_LPIPS = flags.DEFINE_enum("lpips_backbone", None, ["alex", "vgg"],
                           "metrics: LPIPS backbone (default: the run's).")
_DRY_RUN = flags.DEFINE_bool("dry_run", False,
                             "metrics: print only; leave metrics.json.")
_MASK_TAU = flags.DEFINE_float("mask_tau", None, "masks: score threshold "
                               "(default: the run's semantic.tau).")
_CURVE_PNG = flags.DEFINE_string("curve_png", None, "curve: the PNG to write.")
_LABELS = flags.DEFINE_list("labels", None,
                            "curve: legend labels (default: run folders).")
_X_AXIS = flags.DEFINE_enum("x_axis", "seconds", ["seconds", "step"],
                            "curve: x axis.")
_BENCHMARKS = flags.DEFINE_list("benchmarks", None,
                                "figures: benchmark scene folders.")
_FIGURES_DIR = flags.DEFINE_string("figures_dir", None,
                                   "figures: folder for the PNGs.")
_VIEWS = flags.DEFINE_integer("views", 3, "figures: test views (grid rows) "
                              "per benchmark; loss_maps: views per failure "
                              "kind.")
_SET_APART = flags.DEFINE_list(
    "set_apart", None, "seeds: test views (image names, e.g. "
    "1extra003.png) whose difference is reported apart from the others'.")
_CLEAN_RUN = flags.DEFINE_string(
    "clean_run", None, "loss_maps: the run folder of the scene's clean twin "
    "(the same cameras, no transients): what lies behind each transient.")
_FIGURE_DOWNSCALE = flags.DEFINE_integer(
    "figure_downscale", None, "figures: image downscale of the renders "
    "(default: the runs' run.json).")
flags.mark_flags_as_required(["report", "runs"])


def _one_run() -> str:
  cli.require(len(_RUNS.value) == 1, "runs", ",".join(_RUNS.value),
              f"names several folders; --report={_REPORT.value} takes one")
  return _RUNS.value[0]


def _metrics() -> None:
  new, old, source = report.recompute_metrics(
      _one_run(), _GAUSSIANS.value, _LPIPS.value, _DRY_RUN.value)
  print(f"source: {source}; {new['num_views']} test views; LPIPS "
        f"backbone: {new['lpips_net']}")
  for key in ("psnr", "ssim", "lpips"):
    before = "-" if old.get(key) is None else f"{old[key]:.4f}"
    print(f"  {key:6s} now {new[key]:.4f}   stored {before}")


def _masks() -> None:
  out = report.render_masks(_one_run(), _MASK_TAU.value)
  print(f"wrote {out['num_views']} mask renders of "
        f"{out['num_gaussians_above_tau']} Gaussians with s_j > tau = "
        f"{out['tau']:g} to {out['folder']}")
  block = out["mask_iou"]
  if block is None:
    print("the scene has no ground-truth masks: no IoU computed")
    return
  mean = "n/a" if block["mean"] is None else f"{block['mean']:.4f}"
  print(f"mask IoU (alpha > {evaluation.MASK_ALPHA_THRESHOLD}): mean {mean} "
        f"over {block['num_views_scored']} views; "
        f"{out['num_views'] - block['num_views_scored']} views left out (no "
        "transient in the mask or the render); updated metrics.json")


def _fraction(x) -> str:
  return "n/a" if x is None else f"{x:.3f}"


def _evidence() -> None:
  out = ghost_evidence.evidence_report(_one_run())
  print(f"{out['num_ghost']:,} of {out['num_alive']:,} alive Gaussians lie "
        f"on a billboard; over {out['num_views']} training views they carry "
        f"{_fraction(out['ghost_weight_share'])} of all blending weight and "
        f"{_fraction(out['ghost_masked_share'])} of the weight on transient "
        f"pixels, which the render reproduces to "
        f"{_fraction(out['masked_agreement'])} (weighted mean agreement; "
        f"per pixel {_fraction(out['pixel_agreement']['transient'])} on "
        f"transient pixels, {_fraction(out['pixel_agreement']['static'])} "
        "on the rest)")
  blocks = dict(out["rules"])
  if out["run_scores"] is not None:
    blocks["run's own"] = out["run_scores"]
  for name, b in blocks.items():
    g, o = b["ghost"], b["other"]
    print(f"  {name:10s} median s_j ghost {_fraction(g['median'])}, other "
          f"{_fraction(o['median'])}; s_j > {b['tau']:g}: {g['above_tau']:,} "
          f"of {g['num']:,} ghosts, {o['above_tau']:,} of {o['num']:,} others"
          f" (precision {_fraction(b['precision'])}, recall "
          f"{_fraction(b['recall'])})")
  print(f"wrote {ghost_evidence.EVIDENCE_JSON} and "
        f"{ghost_evidence.EVIDENCE_PNG} in {out['workdir']}")


def _loss_maps() -> None:
  cli.require(_VIEWS.value >= 1, "views", _VIEWS.value, "must be positive")
  out = loss_maps.loss_map_report(_one_run(), _VIEWS.value, _CLEAN_RUN.value)
  pooled = out["pooled"]
  print(f"masked {pooled['masked_fraction']:.3f} of the training pixels; "
        + ", ".join(f"{k} {_fraction(pooled[k])}" for k in
                    ("precision", "recall", "iou") if k in pooled))
  if "stages" in pooled:
    print("  recall after each step of the residual map (P / R / IoU): "
          + ", ".join(f"{k} {_fraction(v['precision'])} / "
                      f"{_fraction(v['recall'])} / {_fraction(v['iou'])}"
                      for k, v in pooled["stages"].items()))
  if "contrast" in pooled:
    c = pooled["contrast"]
    print(f"  transient pixels at least {c['threshold']:.3f} from what lies "
          f"behind them: {_fraction(c['reachable'])}; of all, reproduced by "
          f"the model there: {_fraction(c['baked'])}")
  for kind, names in out["worst"].items():
    print(f"  {kind}: {', '.join(names) or '(none)'}")
  print(f"wrote {out['json']}" + (f" and {out['png']}" if out["png"] else ""))


def main(argv):
  cli.no_arguments(argv)
  what = _REPORT.value
  if what == "metrics":
    _metrics()
  elif what == "renders":
    print(f"wrote training-view renders to {report.render_colour(_one_run())}")
  elif what == "masks":
    _masks()
  elif what == "evidence":
    _evidence()
  elif what == "loss_maps":
    _loss_maps()
  elif what == "map_limits":
    print("\n".join(map_limits.summary(map_limits.map_limits_report(
        _one_run()))))
  elif what == "seeds":
    for root in _RUNS.value:
      cli.require_folder("runs", root)
    print(seeds.format_markdown(seeds.seed_table(
        seeds.find_runs(_RUNS.value), set_apart=_SET_APART.value)), end="")
  elif what == "curve":
    cli.require(_CURVE_PNG.value is not None, "curve_png", None,
                "is needed: pass the PNG to write")
    plots.plot([os.path.join(r, run_lib.CURVE_JSON) if os.path.isdir(r)
                else r for r in _RUNS.value], _CURVE_PNG.value,
               _LABELS.value, _X_AXIS.value)
  else:
    cli.require(_BENCHMARKS.value and _FIGURES_DIR.value, "figures_dir",
                _FIGURES_DIR.value, "and --benchmarks are needed")
    cli.require(_VIEWS.value >= 1, "views", _VIEWS.value, "must be positive")
    print("\n".join(figures.make_figures(
        _BENCHMARKS.value, _one_run(), _FIGURES_DIR.value, _VIEWS.value,
        _FIGURE_DOWNSCALE.value)))


if __name__ == "__main__":
  cli.run(main)
