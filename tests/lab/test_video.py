"""Videos of finished runs (clipgs_jax/lab/video.py): camera paths, frames,
MP4 and GIF files, and bad inputs."""

import contextlib
import io
import json
import os

import imageio_ffmpeg
import numpy as np
from PIL import Image
import pytest

from clipgs_jax import camera
from clipgs_jax import checkpoint
from clipgs_jax import cli
from clipgs_jax import config
from clipgs_jax import evaluation
from clipgs_jax import fileio
from clipgs_jax import guidance_config
from clipgs_jax import run as run_lib
from clipgs_jax import train
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.lab import video
import test_transforms  # pylint: disable=g-bad-import-order


def _stack(cams):
  return video._stack(cams)  # pylint: disable=protected-access


def test_orbit_fits_the_ring_of_cameras():
  # Radius 3 at height 1, facing (0, 0, 0).
  cams = _stack(test_transforms.ring(12))
  path = video.orbit(cams, 24)
  centres = camera.camera_center(path)
  np.testing.assert_allclose(np.linalg.norm(centres[:, :2], axis=1), 3.0,
                             rtol=1e-5)
  np.testing.assert_allclose(centres[:, 2], 1.0, atol=1e-5)
  # It starts at the first camera and turns the way the captures do.
  np.testing.assert_allclose(centres[0], camera.camera_center(
      camera.camera_at(cams, 0)), atol=1e-5)
  np.testing.assert_allclose(centres[2], camera.camera_center(
      camera.camera_at(cams, 1)), atol=1e-5)
  # Every frame looks at the point the cameras look at, the right way up.
  axes = np.asarray(path.rotation)[:, 2]
  towards = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
  np.testing.assert_allclose(np.sum(axes * towards, 1), 1.0, atol=1e-5)
  assert np.all(-np.asarray(path.rotation)[:, 1, 2] > 0)


def test_orbit_of_cameras_on_a_line_or_at_one_point():
  ring = test_transforms.ring(4)
  line = video.orbit(_stack([ring[0], ring[2]]), 8)
  assert np.all(np.isfinite(np.asarray(line.translation)))
  with pytest.raises(ValueError, match="share one position"):
    video.orbit(_stack([ring[0], ring[0]]), 8)


def test_through_passes_every_camera():
  cams = _stack(test_transforms.ring(5)[:4])
  path = video.through(cams, 3 * 3 + 1)   # 3 frames per gap
  for k in range(4):
    key = camera.camera_at(cams, k)
    got = camera.camera_at(path, 3 * k)
    np.testing.assert_allclose(got.rotation, key.rotation, atol=1e-5)
    np.testing.assert_allclose(got.translation, key.translation, atol=1e-4)
  # Between two cameras the centre stays near their ring.
  radius = np.linalg.norm(camera.camera_center(path)[:, :2], axis=1)
  assert np.all(np.abs(radius - 3.0) < 0.3)


def _fake_run(root, name="run", scene_dir=None) -> str:
  """A run folder of the tiny transforms scene at its initial Gaussians:
  what video.py reads from a finished run, without training."""
  scene_dir = scene_dir or os.path.join(root, "scene")
  if not os.path.isdir(scene_dir):
    test_transforms.write_transforms(scene_dir, 5)
  scene = scene_lib.load_scene(scene_dir)
  cfg = config.Config(gaussians=config.GaussiansConfig(sh_degree=0,
                                                       min_capacity=64,
                                                       random_init_points=40),
                      semantic=guidance_config.SemanticConfig(scorer="oracle"),
                      train=config.TrainConfig(background=scene.background))
  cfg = train.resolve(cfg, scene)
  workdir = os.path.join(root, name)
  fileio.write_json(os.path.join(workdir, run_lib.RUN_JSON),
                    {"scene": scene_dir, "downscale": 1})
  fileio.write_json(os.path.join(workdir, run_lib.CONFIG_JSON),
                    config.to_dict(cfg))
  checkpoint.save(os.path.join(workdir, train.CHECKPOINT_NAME),
                  train.initial_state(cfg, scene), cfg)
  return workdir


def test_gif_side_by_side_with_scores(tmp_path):
  run = _fake_run(str(tmp_path))
  out = str(tmp_path / "v.gif")
  plan = video.plan(run, run, "orbit", 1.0, 4.0, out, scores=True)
  info = video.write(plan, progress=False)
  with Image.open(out) as gif:
    assert gif.n_frames == 4 and gif.info["duration"] == 250
    # Two 32-pixel panels under their labels.
    assert info["size"][0] == 64 and gif.size == tuple(info["size"])


# Reading the file back forks ffmpeg: a fork-then-exec, which JAX's
# at-fork hook warns about anyway (video.py silences it the same way).
@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")
def test_mp4_of_the_training_path(tmp_path):
  run = _fake_run(str(tmp_path))
  out = str(tmp_path / "v.mp4")
  video.write(video.plan(run, None, "train", 0.5, 10.0, out),
              progress=False)
  assert imageio_ffmpeg.count_frames_and_secs(out) == (5, 0.5)
  assert sorted(os.listdir(tmp_path)) == ["run", "scene", "v.mp4"]


def test_a_failure_while_rendering_leaves_nothing(tmp_path, monkeypatch):
  run = _fake_run(str(tmp_path))
  calls = []

  def fail_on_third(*args):
    calls.append(1)
    if len(calls) == 3:
      raise OSError(28, "No space left on device")
    return real(*args)
  real = evaluation.render_camera
  monkeypatch.setattr(evaluation, "render_camera", fail_on_third)
  with pytest.raises(OSError):
    video.write(video.plan(run, None, "orbit", 1.0, 5.0,
                           str(tmp_path / "v.mp4")), progress=False)
  assert sorted(os.listdir(tmp_path)) == ["run", "scene"]


def _one_line(fn) -> str:
  """fn under the scripts' error path: its one stderr line."""
  err = io.StringIO()
  with contextlib.redirect_stderr(err), pytest.raises(SystemExit) as e:
    cli.guarded(lambda argv: fn())(["prog"])
  assert e.value.code == cli.EXIT_ERROR
  lines = err.getvalue().splitlines()
  assert len(lines) == 1 and lines[0].startswith("error: "), lines
  return lines[0]


@pytest.mark.parametrize("kwargs, says", [
    ({"fps": 0}, ("--fps=0", "positive")),
    ({"seconds": 0.01}, ("--seconds=0.01", "at least 2")),
    ({"path": "spiral"}, ("--path=spiral", "orbit, train, test")),
    ({"out": "v.avi"}, ("--out=", "v.avi", ".mp4 or .gif")),
    ({"out": "missing/v.mp4"}, ("missing", "create it")),
    ({"run": "nothing"}, ("nothing", "does not exist")),
    ({"compare": "other"}, ("--compare=", "other", "same scene")),
])
def test_bad_inputs_end_in_one_line_before_any_load(tmp_path, kwargs, says):
  run = _fake_run(str(tmp_path))
  _fake_run(str(tmp_path), "other", str(tmp_path / "other_scene"))
  args = dict(run=run, compare=None, path="orbit", seconds=1.0, fps=5.0,
              out="v.mp4")
  args.update(kwargs)
  for key in ("run", "compare", "out"):
    if args[key] is not None and not os.path.isabs(args[key]):
      args[key] = str(tmp_path / args[key])
  before = sorted(os.listdir(tmp_path))
  line = _one_line(lambda: video.plan(**args))
  for text in says:
    assert text in line, line
  assert sorted(os.listdir(tmp_path)) == before


def test_a_path_needs_two_cameras(tmp_path):
  scene_dir = str(tmp_path / "scene")
  test_transforms.write_transforms(scene_dir, 3,
                                   name="transforms_train.json")
  test_transforms.write_transforms(scene_dir, 1, name="transforms_test.json",
                                   first=3)
  run = _fake_run(str(tmp_path), scene_dir=scene_dir)
  line = _one_line(lambda: video.write(video.plan(
      run, None, "test", 1.0, 5.0, str(tmp_path / "v.mp4")), progress=False))
  assert "1 test view" in line and "--path" in line
  assert not os.path.exists(tmp_path / "v.mp4")
  with open(os.path.join(run, run_lib.RUN_JSON)) as f:
    assert json.load(f)["scene"] == scene_dir
