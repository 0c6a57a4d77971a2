"""Trains what a config file describes: one run, or a sweep of runs.

  python experiments/train.py --workdir=DIR [--config=configs/NAME.py]
      [--scene=DIR|PACK.npz] [--resume] [--clip_weights=PATH]
      [--config.train.steps=N] [--config.semantic.scorer=oracle] ...
      [--config.train.batch_size=B] [--coordinator_address=HOST:PORT
      --num_processes=N --process_id=I]

--config (default configs/default.py: the 3DGS paper values; the embedded
scene at default_scene.TRAIN_STEPS steps without --scene) is an
ml_collections config file; every field is overridable as
--config.SECTION.FIELD=VALUE (see clipgs_jax/config.py for the fields).
configs/smoke.py is a tiny CI run, configs/benchmark.py one benchmark run:
one run is run.train_and_evaluate, which writes its folder as
clipgs_jax/run.py describes (config.json, metrics.json, curve.json,
checkpoint.npz, renders/, ...). configs/table.py, ablate.py, tau_sweep.py
and demo.py have a `sweep` section (rows x benchmarks;
--scene=BENCH[,BENCH...]): clipgs_jax/lab/sweep.py runs their rows into
DIR/<bench>/<row>/ and writes their table into DIR.
"""

import json
import os
import sys

from absl import flags
import ml_collections
from ml_collections import config_flags

from clipgs_jax import cli
from clipgs_jax import config_file
from clipgs_jax import run
from clipgs_jax import sharding
from clipgs_jax.lab import sweep

# Next to this script, so that a non-editable install finds it too.
DEFAULT_CONFIG = os.path.join(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__))), "configs", "default.py")
_CONFIG = cli.define_config_file(
    "config", DEFAULT_CONFIG,
    "Config file (configs/*.py); override any field as "
    "--config.train.steps=7000.")
flags.declare_key_flag("config")     # listed by --helpshort
_WORKDIR = flags.DEFINE_string("workdir", None, "Output folder (a sweep: "
                               "the root of its rows and table).")
_SCENE = flags.DEFINE_string(
    "scene", None, "Scene folder (images/ + sparse/0/) or its pack (.npz "
    "from prepare.py --prepare=pack), default: the embedded scene; a sweep: "
    "its benchmarks, comma-separated.")
_RESUME = flags.DEFINE_bool("resume", False, "Continue from "
                            "workdir/checkpoint.npz (sweep rows always do).")
_CLIP_WEIGHTS = flags.DEFINE_string(
    "clip_weights", None, "CLIP weights for clip scorers (OpenAI .pt, HF "
    "safetensors or directory, or .npz); default $CLIPGS_CLIP_WEIGHTS.")
_COORDINATOR = flags.DEFINE_string(
    "coordinator_address", None, "Multi-host: host:port of process 0 "
    "(default $JAX_COORDINATOR_ADDRESS); every process runs this command "
    "with the same flags and its own --process_id.")
_NUM_PROCESSES = flags.DEFINE_integer(
    "num_processes", None, "Multi-host: the number of processes (default: "
    "from the cluster, e.g. SLURM).")
_PROCESS_ID = flags.DEFINE_integer(
    "process_id", None, "Multi-host: this process's index, 0 writes the "
    "run folder (default: from the cluster).")
flags.mark_flag_as_required("workdir")


def main(argv):
  cli.no_arguments(argv)
  sharding.join(_COORDINATOR.value, _NUM_PROCESSES.value, _PROCESS_ID.value)
  cd = ml_collections.ConfigDict(_CONFIG.value.to_dict())   # unlocked
  run_info = {"config": config_flags.get_config_filename(
      flags.FLAGS["config"]), "argv": sys.argv}
  if "sweep" in cd:                  # rows x benchmarks, then their table
    if _SCENE.value is not None:
      cd.sweep.benchmarks = _SCENE.value
    print(json.dumps(sweep.run(cd, _WORKDIR.value,
                               clip_weights=_CLIP_WEIGHTS.value,
                               run_info=run_info), indent=1))
    return
  if _SCENE.value is not None:
    cd.data.scene = _SCENE.value
  out = run.train_and_evaluate(
      config_file.check(cd), _WORKDIR.value, resume=_RESUME.value,
      clip_weights=_CLIP_WEIGHTS.value, run_info=run_info)
  if not sharding.is_writer():
    return
  print(json.dumps({k: out[k] for k in ("train_seconds", "steps",
                                        "num_gaussians")}
                   | {f"test.{k}": out["test"][k]
                      for k in ("psnr", "ssim", "lpips", "lpips_net")}))


if __name__ == "__main__":
  cli.run(main)
