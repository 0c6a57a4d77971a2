"""Every bad input ends in one line on stderr, an exit code, and no litter.

One test per kind of bad input. Most rows run the library call under
cli.guarded and cli.output_dir in this process, which is what each script's
main does around it (experiments/train.py: flags, scene, weights, then the
workdir); a few rows run experiments/train.py itself, for what only the
script can show (flag parsing, the order of its checks, --debug).
Each test asserts the exit code, exactly one line of error output naming
the input, and that no output folder or partial file remains.
"""

import contextlib
import dataclasses
import errno
import hashlib
import io
import os
import pathlib
import re
import subprocess
import sys
from unittest import mock

import numpy as np
import pycolmap
from absl.testing import absltest

from clipgs_jax import checkpoint
from clipgs_jax import cli
from clipgs_jax import config
from clipgs_jax import fileio
from clipgs_jax import gaussians
from clipgs_jax import ply
from clipgs_jax import train
from clipgs_jax.clip import weights
from clipgs_jax.data import images
from clipgs_jax.data import scene as scene_lib
from test_scene import write_scene  # pylint: disable=g-bad-import-order

ROOT = pathlib.Path(__file__).resolve().parents[1]
# Nine views of a tiny PINHOLE scene: test views 0 and 8, seven training.
NAMES = tuple(f"img{i:02d}.png" for i in range(9))
SIZE = (16, 12)
# If set, every row appends "<test>: <its line>" to this file (the table in
# the lab notebook is made from it).
REPORT_ENV = "CLIPGS_BAD_INPUTS_REPORT"
# absl's log lines (I1122 12:00:00.000 ...) may precede the error line.
_ABSL_LOG = re.compile(r"^[IWEF]\d{4} ")


def _tree(root: str) -> dict[str, str]:
  """{relative path: sha1} of every file below `root`."""
  out = {}
  for folder, _, files in os.walk(root):
    for name in files:
      path = os.path.join(folder, name)
      with open(path, "rb") as f:
        out[os.path.relpath(path, root)] = hashlib.sha1(f.read()).hexdigest()
  return out


def _report(test_id: str, line: str) -> None:
  if os.environ.get(REPORT_ENV):
    with open(os.environ[REPORT_ENV], "a") as f:
      f.write(f"{test_id.split('.')[-1]}: {line}\n")


def _tiny_cfg() -> config.Config:
  return config.Config(
      gaussians=config.GaussiansConfig(capacity=8, sh_degree=1),
      scene_extent=1.0)


def _state():
  return train.init_state(_tiny_cfg(), *gaussians.empty(8, 1))


class _InProcess(absltest.TestCase):
  """The scripts' error path around a library call, in this process."""

  def setUp(self):
    super().setUp()
    self.tmp = self.create_tempdir().full_path
    self.scene = os.path.join(self.tmp, "scene")
    self.workdir = os.path.join(self.tmp, "run")
    self.cache = os.path.join(self.tmp, "cache")

  def write_scene(self, names=NAMES, size=SIZE):
    write_scene(self.scene, list(names), cams=(size,))

  def load(self, **kwargs):
    return scene_lib.load_scene(self.scene, cache_dir=self.cache, **kwargs)

  def assert_one_line(self, fn, *, code=cli.EXIT_ERROR, says=(),
                      workdir_kept=False):
    """Runs fn under the scripts' error path; checks the report and litter.

    fn runs inside cli.output_dir(workdir, keep=checkpoint), as
    experiments/train.py's training does, so even a failure at that point
    must leave no output folder.
    """
    before = _tree(self.tmp)

    def main(argv):
      del argv
      with cli.output_dir(self.workdir, keep=train.CHECKPOINT_NAME):
        fn()
    err = io.StringIO()
    with contextlib.redirect_stderr(err), self.assertRaises(
        SystemExit) as cm:
      cli.guarded(main)(["prog"])
    lines = err.getvalue().splitlines()
    self.assertEqual(cm.exception.code, code, lines)
    self.assertLen(lines, 1, lines)
    self.assertStartsWith(lines[0], "error: ")
    for text in says:
      self.assertIn(text, lines[0])
    _report(self.id(), lines[0])
    after = _tree(self.tmp)
    self.assertEqual(os.path.isdir(self.workdir), workdir_kept)
    # Nothing half-written anywhere; the inputs are unchanged.
    self.assertEmpty([p for p in after if ".tmp" in p], after)
    self.assertEqual({p: h for p, h in after.items()
                      if not p.startswith("cache")},
                     {p: h for p, h in before.items()
                      if not p.startswith("cache")})
    return lines[0]



class BadInputTest(_InProcess):
  """Rows that run in this process."""

  def test_valid_scene_loads(self):
    # The control row: the harness passes a good input.
    self.write_scene()
    scene = self.load()
    self.assertLen(scene.train.names, 7)

  def test_truncated_cameras_bin(self):
    self.write_scene()
    path = os.path.join(self.scene, "sparse", "0", "cameras.bin")
    data = pathlib.Path(path).read_bytes()
    pathlib.Path(path).write_bytes(data[: len(data) // 2])
    self.assert_one_line(self.load, says=("cameras.bin", "ends early",
                                          "re-export cameras.bin"))

  def test_missing_image(self):
    self.write_scene()
    os.remove(os.path.join(self.scene, "images", "img03.png"))
    self.assert_one_line(self.load, says=("img03.png", "restore it"))

  def test_image_of_wrong_size(self):
    self.write_scene()
    images.write_png(os.path.join(self.scene, "images", "img03.png"),
                     np.zeros((10, 20, 3)))
    self.assert_one_line(self.load, says=("img03.png", "20x10",
                                          "replace the image"))

  def test_empty_images_folder(self):
    self.write_scene()
    for name in NAMES:
      os.remove(os.path.join(self.scene, "images", name))
    self.assert_one_line(self.load, says=("images is empty",
                                          "put the photos"))

  def test_zero_registered_images(self):
    self.write_scene()
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(
        camera_id=1, model="PINHOLE", width=16, height=12,
        params=[40.0, 41.0, 8, 6]))
    rec.write_binary(os.path.join(self.scene, "sparse", "0"))
    self.assert_one_line(self.load, says=("no registered images",
                                          "re-run COLMAP"))

  def test_all_views_are_test_views(self):
    self.write_scene(names=("extra000.png", "extra001.png"))
    self.assert_one_line(self.load, says=("no training views",
                                          "clutter"))

  def test_unreadable_image(self):
    self.write_scene()
    path = os.path.join(self.scene, "images", "img03.png")
    os.chmod(path, 0)
    self.addCleanup(os.chmod, path, 0o644)
    real_access = os.access
    # root reads any file; pretend to be a user for this one.
    as_user = lambda p, mode: (p != path) and real_access(p, mode)
    with mock.patch.object(images.os, "access", as_user):
      self.assert_one_line(self.load, says=("img03.png", "not readable",
                                            "chmod"))

  def test_png_that_is_not_a_png(self):
    self.write_scene()
    pathlib.Path(self.scene, "images", "img03.png").write_text("not a png")
    self.assert_one_line(self.load, says=("img03.png", "cannot read image",
                                          "re-save it"))

  def test_one_pixel_image(self):
    self.write_scene(size=(1, 1))
    self.assert_one_line(self.load, says=("1x1", "at least 11x11",
                                          "--config.data.downscale"))

  def test_empty_points3d_bin(self):
    self.write_scene()
    pathlib.Path(self.scene, "sparse", "0", "points3D.bin").write_bytes(b"")
    self.assert_one_line(self.load, says=("points3D.bin", "empty",
                                          "re-export points3D.bin"))

  def test_prescaled_folder_of_wrong_size(self):
    self.write_scene(size=(32, 24))
    folder = os.path.join(self.scene, "images_2")
    for name in NAMES:               # 1/4 size where 1/2 is expected
      images.write_png(os.path.join(folder, name), np.zeros((6, 8, 3)))
    self.assert_one_line(lambda: self.load(downscale=2),
                         says=("images_2", "8x6", "not about 1/2",
                               "delete the pre-scaled folder"))

  def test_corrupted_checkpoint_on_resume(self):
    os.makedirs(self.workdir)
    path = os.path.join(self.workdir, train.CHECKPOINT_NAME)
    checkpoint.save(path, _state(), _tiny_cfg())
    data = pathlib.Path(path).read_bytes()
    pathlib.Path(path).write_bytes(data[: len(data) // 2])   # cut short
    line = self.assert_one_line(
        lambda: checkpoint.restore(path, _state()), workdir_kept=True,
        says=(path, "unreadable", "delete it"))
    self.assertNotIn("allow_pickle", line)

  def test_resume_with_another_config(self):
    os.makedirs(self.workdir)
    path = os.path.join(self.workdir, train.CHECKPOINT_NAME)
    checkpoint.save(path, _state(), _tiny_cfg())
    other = dataclasses.replace(_tiny_cfg(),
                                train=config.TrainConfig(seed=1))
    self.assert_one_line(
        lambda: checkpoint.check_resumable(path, other), workdir_kept=True,
        says=(path, "different config", "train.seed: 0 -> 1",
              "new workdir"))

  def test_disk_full_during_checkpoint_write(self):
    os.makedirs(self.workdir)
    path = os.path.join(self.workdir, train.CHECKPOINT_NAME)
    checkpoint.save(path, _state(), _tiny_cfg())
    with open(path, "rb") as f:
      saved = f.read()

    def full_disk(f, **arrays):
      del arrays
      f.write(b"PK\x03\x04 partial")
      raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    newer = _state().replace(step=np.int32(7))
    with mock.patch.object(checkpoint.np, "savez", full_disk):
      self.assert_one_line(
          lambda: checkpoint.save(path, newer, _tiny_cfg()),
          workdir_kept=True,
          says=("No space left on device", path, "free space"))
    # The previous checkpoint survives, byte for byte, and still loads.
    with open(path, "rb") as f:
      self.assertEqual(f.read(), saved)
    self.assertEqual(int(checkpoint.restore(path, _state())[0].step), 0)

  def test_failure_after_workdir_creation_removes_it(self):
    # A run that fails after creating its workdir, before any checkpoint.
    def fail():
      fileio.write_json(os.path.join(self.workdir, "run.json"), {})
      raise FloatingPointError("train: non-finite loss at step 3; lower the "
                               "learning rates")
    self.assert_one_line(fail, says=("non-finite loss",))

  def test_unexpected_arguments_are_a_usage_error(self):
    self.assert_one_line(lambda: cli.no_arguments(["prog", "x"]),
                         code=cli.EXIT_USAGE, says=("unexpected arguments",))

  def test_ply_with_non_finite_values(self):
    params, alive = gaussians.empty(5, 0)
    means = np.zeros((5, 3), np.float32)
    means[1, 0], means[3, 2] = np.nan, np.inf
    params = params.replace(means=means, opacity_logits=np.asarray(
        [0, 0, 0, 0, -np.inf], np.float32))
    path = os.path.join(self.tmp, "in.ply")
    ply.write_ply(path, params, np.ones(5, bool))
    self.assert_one_line(lambda: ply.read_ply(path),
                         says=("in.ply", "3 of 5 vertices", "x in 1 rows",
                               "z in 1 rows", "opacity in 1 rows",
                               "first row 1"))


class BadWeightsTest(_InProcess):
  """A weights file that is not what its extension says."""

  def assert_weights_line(self, name, content, fmt):
    path = os.path.join(self.tmp, name)
    pathlib.Path(path).write_bytes(content)
    line = self.assert_one_line(lambda: weights.read_tensors(path),
                                says=(path, f"cannot be read as {fmt}",
                                      "pass CLIP ViT-B/32 weights"))
    # Never advise loading that can run code from the file.
    for unsafe in ("weights_only", "allow_pickle", "trust"):
      self.assertNotIn(unsafe, line)
    return line

  def test_safetensors_with_bad_content(self):
    line = self.assert_weights_line("clip.safetensors", b"\x01\x00",
                                    "safetensors")
    self.assertIn("SafetensorError", line)

  def test_pt_with_bad_content(self):
    self.assert_weights_line("clip.pt", b"\x80\x02 not a pickle",
                             "a PyTorch checkpoint")

  def test_pt_with_a_pickled_class(self):
    import torch  # pylint: disable=g-import-not-at-top
    path = os.path.join(self.tmp, "evil.pt")
    torch.save({"w": torch.zeros(1), "x": _Unsafe()}, path)
    line = self.assert_one_line(lambda: weights.read_tensors(path),
                                says=(path, "Unsupported global"))
    self.assertNotIn("weights_only", line)

  def test_npz_with_pickled_arrays(self):
    path = os.path.join(self.tmp, "clip.npz")
    np.savez(path, x=np.asarray([{"a": 1}], dtype=object))
    line = self.assert_one_line(lambda: weights.read_tensors(path),
                                says=(path, "a numpy .npz",
                                      "pickled Python objects"))
    self.assertNotIn("allow_pickle", line)

  def test_text_file_with_a_weights_extension(self):
    for name, fmt in (("notes.safetensors", "safetensors"),
                      ("notes.pt", "a PyTorch checkpoint"),
                      ("notes.npz", "a numpy .npz")):
      line = self.assert_weights_line(name, b"some notes, not weights\n", fmt)
      self.assertIn("holds text", line)


class OutputDirTest(absltest.TestCase):
  """cli.output_dir removes exactly what a failed run created."""

  def test_existing_folder_keeps_what_was_there(self):
    root = self.create_tempdir().full_path
    pathlib.Path(root, "notes.txt").write_text("mine")
    with self.assertRaises(ValueError):
      with cli.output_dir(root, keep=train.CHECKPOINT_NAME):
        pathlib.Path(root, "run.json").write_text("{}")
        os.makedirs(os.path.join(root, "renders", "test"))
        raise ValueError("bad input")
    self.assertEqual(os.listdir(root), ["notes.txt"])

  def test_folder_with_a_checkpoint_stays(self):
    # A run that fails after its first checkpoint can be resumed.
    root = os.path.join(self.create_tempdir().full_path, "run")
    with self.assertRaises(FloatingPointError):
      with cli.output_dir(root, keep=train.CHECKPOINT_NAME):
        pathlib.Path(root, train.CHECKPOINT_NAME).write_bytes(b"ckpt")
        raise FloatingPointError("non-finite loss")
    self.assertEqual(os.listdir(root), [train.CHECKPOINT_NAME])

  def test_a_file_is_not_a_folder(self):
    path = self.create_tempfile().full_path
    with self.assertRaisesRegex(ValueError, "is a file; pass a new or "
                                "existing folder"):
      with cli.output_dir(path):
        pass

  def test_bugs_keep_their_traceback(self):
    # Only user errors become one line; a bug propagates unchanged.
    with self.assertRaises(ZeroDivisionError):
      cli.guarded(lambda argv: 1 / 0)(["prog"])


class _Unsafe:
  """A class that a weights-only unpickler must refuse."""


def _run_train(*flags, env=None):
  """experiments/train.py as a subprocess: (exit code, stderr lines)."""
  env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu",
             CLIPGS_CLIP_WEIGHTS="") | (env or {})
  proc = subprocess.run(
      [sys.executable, str(ROOT / "experiments" / "train.py"), *flags],
      capture_output=True, text=True, env=env, cwd=ROOT, check=False)
  lines = [l for l in proc.stderr.splitlines() if not _ABSL_LOG.match(l)]
  return proc.returncode, lines, proc.stderr


class TrainScriptTest(absltest.TestCase):
  """Rows that need the script: flags, check order, --debug."""

  def setUp(self):
    super().setUp()
    self.tmp = self.create_tempdir().full_path
    self.scene = os.path.join(self.tmp, "scene")
    self.workdir = os.path.join(self.tmp, "run")
    write_scene(self.scene, list(NAMES), cams=(SIZE,))
    self.env = {"CLIPGS_JAX_CACHE": os.path.join(self.tmp, "cache")}

  def run_train(self, *flags, code, says=()):
    status, lines, stderr = _run_train(f"--workdir={self.workdir}", *flags,
                                       env=self.env)
    self.assertEqual(status, code, stderr)
    self.assertLen(lines, 1, stderr)
    self.assertStartsWith(lines[0], "error: ")
    self.assertNotIn("Traceback", stderr)
    for text in says:
      self.assertIn(text, lines[0])
    _report(self.id(), lines[0])
    self.assertFalse(os.path.exists(self.workdir))
    return lines[0]

  def test_downscale_zero(self):
    self.run_train(f"--scene={self.scene}", "--config.data.downscale=0",
                   code=cli.EXIT_USAGE,
                   says=("--config.data.downscale=0", "positive integer"))

  def test_unparsable_flag(self):
    # absl's parse error, without its help hint line.
    self.run_train(f"--scene={self.scene}", "--config.train.steps=abc",
                   code=cli.EXIT_USAGE, says=("--config.train.steps=abc",
                                              "invalid literal", "--helpshort"))

  def test_flags_are_checked_before_the_scene(self):
    # The scene is broken too, but the flag is reported: nothing was read.
    os.remove(os.path.join(self.scene, "sparse", "0", "cameras.bin"))
    self.run_train(f"--scene={self.scene}", "--config.train.steps=0",
                   code=cli.EXIT_USAGE,
                   says=("--config.train.steps=0 must be positive",))

  def test_bad_scene_through_the_script(self):
    path = os.path.join(self.scene, "sparse", "0", "cameras.bin")
    data = pathlib.Path(path).read_bytes()
    pathlib.Path(path).write_bytes(data[: len(data) // 2])
    self.run_train(f"--scene={self.scene}", code=cli.EXIT_ERROR,
                   says=("corrupt COLMAP file", path))
    # --debug adds the traceback before the same line.
    status, lines, stderr = _run_train(
        f"--workdir={self.workdir}", f"--scene={self.scene}", "--debug",
        env=self.env)
    self.assertEqual(status, cli.EXIT_ERROR)
    self.assertIn("Traceback", stderr)
    self.assertStartsWith(stderr.splitlines()[-1], "error: corrupt COLMAP")
    self.assertFalse(os.path.exists(self.workdir))

  def test_bad_weights_through_the_script(self):
    path = os.path.join(self.tmp, "clip.safetensors")
    pathlib.Path(path).write_text("not weights")
    line = self.run_train(f"--scene={self.scene}",
                          "--config.semantic.scorer=clip",
                          f"--clip_weights={path}", code=cli.EXIT_USAGE,
                          says=("--config.semantic.scorer=clip", path,
                                "safetensors",
                                "pass CLIP ViT-B/32 weights"))
    self.assertNotIn("weights_only", line)

  def test_missing_clip_weights_is_the_only_line(self):
    # Checked before the (broken) scene loads; JAX probes every backend
    # (JAX_PLATFORMS unset), and its notices stay hidden.
    os.remove(os.path.join(self.scene, "sparse", "0", "cameras.bin"))
    status, _, stderr = _run_train(
        f"--workdir={self.workdir}", f"--scene={self.scene}",
        "--config.semantic.scorer=clip",
        env=dict(self.env, JAX_PLATFORMS=""))
    self.assertEqual(status, cli.EXIT_USAGE, stderr)
    self.assertLen(stderr.splitlines(), 1, stderr)
    self.assertStartsWith(stderr, "error: --config.semantic.scorer=clip: "
                          "CLIP weights are needed")
    self.assertFalse(os.path.exists(self.workdir))

  def test_transforms_without_frames_through_the_script(self):
    scene = os.path.join(self.tmp, "blender")
    os.makedirs(scene)
    pathlib.Path(scene, "transforms.json").write_text(
        '{"camera_angle_x": 0.7, "frames": []}')
    self.run_train(f"--scene={scene}", code=cli.EXIT_ERROR,
                   says=("transforms.json has no frames", "file_path"))

  def test_sweep_without_benchmarks(self):
    self.run_train("--config=configs/table.py", code=cli.EXIT_USAGE,
                   says=("--config.sweep.benchmarks", "--scene="))

  def test_sweep_with_bad_taus(self):
    self.run_train("--config=configs/tau_sweep.py", f"--scene={self.scene}",
                   "--config.sweep.taus=0.1,abc", code=cli.EXIT_USAGE,
                   says=("--config.sweep.taus=0.1,abc", "numbers"))

  def test_resume_with_another_config_keeps_the_run(self):
    os.makedirs(self.workdir)
    path = os.path.join(self.workdir, train.CHECKPOINT_NAME)
    checkpoint.save(path, _state(), _tiny_cfg())
    before = _tree(self.workdir)
    status, lines, stderr = _run_train(
        f"--workdir={self.workdir}", f"--scene={self.scene}",
        "--config=configs/smoke.py", "--resume", env=self.env)
    self.assertEqual(status, cli.EXIT_ERROR, stderr)
    self.assertLen(lines, 1, stderr)
    self.assertIn("different config", lines[0])
    _report(self.id(), lines[0])
    # Nothing in the run folder was touched (no config.json rewritten).
    self.assertEqual(_tree(self.workdir), before)


if __name__ == "__main__":
  absltest.main()
