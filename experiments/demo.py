"""The README main job: vanilla 3DGS against localized guidance, side by side.

  python experiments/demo.py --workdir=DIR [--clip_weights=FILE]

Trains on the embedded default scene twice with the same settings: vanilla
3DGS, and localized semantic guidance (per-pixel evidence; the
ground-truth masks, labelled ORACLE-PIXEL, unless CLIP weights are given,
then dense CLIP). Writes DIR/vanilla/ and DIR/guided/ (each a full run
folder, see clipgs_jax/run.py), DIR/comparison.png (one test view: vanilla,
guided, ground truth, with their PSNR) and DIR/comparison.json (both
runs' test metrics and run times).
"""

import dataclasses
import json
import os

from absl import flags
import numpy as np

from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax import fileio
from clipgs_jax import guidance
from clipgs_jax import plots
from clipgs_jax import run as run_lib
from clipgs_jax import train
from clipgs_jax.data import default_scene
from clipgs_jax.data import images as images_lib
from clipgs_jax.data import scene as scene_lib

_WORKDIR = flags.DEFINE_string("workdir", None, "Output folder.")
_CLIP_WEIGHTS = flags.DEFINE_string(
    "clip_weights", None, "CLIP weights (OpenAI .pt, HF safetensors, .npz): "
    "guidance by dense CLIP instead of the ORACLE-PIXEL masks.")
flags.mark_flag_as_required("workdir")

# Loss masking on: measured on this scene in BUILD_NOTES ("Localized
# evidence"); without it pruned ghosts regrow from the photometric loss.
LOSS_MASKING = True


def configs(steps: int, use_clip: bool
            ) -> dict[str, config_lib.Config]:
  """The two runs' configs: identical except for the semantic stage."""
  base = config_lib.Config(train=config_lib.TrainConfig(
      steps=steps, eval_every=max(1, steps // 10),
      checkpoint_every=steps))
  sem = config_lib.SemanticConfig(
      scorer="clip" if use_clip else "oracle", evidence="pixel",
      loss_masking=LOSS_MASKING).scaled_to(steps)
  return {"vanilla": base,
          "guided": dataclasses.replace(base, semantic=sem)}


def main(argv):
  cli.no_arguments(argv)
  workdir = os.path.abspath(_WORKDIR.value)
  use_clip = bool(_CLIP_WEIGHTS.value)
  cfgs = configs(default_scene.TRAIN_STEPS, use_clip)
  scene_path = default_scene.ensure_default_scene()
  scene = scene_lib.load_scene(scene_path)
  # Weights (if any) are read before anything is written.
  scorers = {name: guidance.make_scorer(cfg.semantic, scene,
                                        clip_weights=_CLIP_WEIGHTS.value)
             for name, cfg in cfgs.items()}
  metrics = {}
  for name, cfg in cfgs.items():
    out = os.path.join(workdir, name)
    with cli.output_dir(out, keep=train.CHECKPOINT_NAME):
      metrics[name] = run_lib.train_and_evaluate(
          cfg, scene, out, scorer=scorers[name],
          run_info={"scene": scene_path, "embedded_scene": True,
                    "downscale": 1, "train_split": "clutter"})
  # The test view where guidance changes PSNR most, to show what it does.
  names = scene.test.names
  psnr = {k: np.array([m["test"]["per_image"][n]["psnr"] for n in names])
          for k, m in metrics.items()}
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
  print(json.dumps(summary, indent=1))


if __name__ == "__main__":
  cli.run(main)
