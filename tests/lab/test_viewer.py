"""The viewer of a finished run: in headless Chromium, in-process, errors.

One guided smoke run (ORACLE-PIXEL on the embedded scene, so s_j, masks and
pruned rows exist) is trained for the whole file by experiments/train.py.
"""

import dataclasses
import os
import shutil
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import viser

import browser
from clipgs_jax import cli
from clipgs_jax import evaluation
from clipgs_jax import guidance
from clipgs_jax import ply
from clipgs_jax import run as run_lib
from clipgs_jax import summary
from clipgs_jax.lab import viewed_run
from clipgs_jax.lab import viewer
from clipgs_jax.maps import residual

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__))))
# Half-size images: 35 s of CPU to train, against 37-63 s at full size.
GUIDED_SMOKE = ("--config=configs/smoke.py", "--config.semantic.scorer=oracle",
                "--config.semantic.evidence=pixel",
                "--config.semantic.scale_schedule=True",
                "--config.data.downscale=2")
# A pixel "differs" when a channel moves by more than this (of 255): well
# above JPEG-free screenshot noise, far below splat-versus-white contrast.
PIXEL_DIFFERENCE = 24
# The splats cover most of the first training view of the embedded scene;
# an empty or undrawn canvas covers none.
MIN_SPLAT_FRACTION = 0.3
# Colouring by s_j (viridis) changes most splat pixels; measured 0.9.
MIN_TOGGLE_FRACTION = 0.2
WAIT_S = 90.0                  # for the page to draw (swiftshader is slow)


def _in_ci() -> bool:
  """CI=1 (.ci/run sets it; most CI services set CI=true): a missing
  browser fails the browser test instead of skipping it."""
  return os.environ.get("CI", "").lower() not in ("", "0", "false")


def _env():
  return dict(os.environ, PYTHONPATH=ROOT, JAX_PLATFORMS="cpu")


@pytest.fixture(scope="module")
def guided_run(tmp_path_factory):
  workdir = str(tmp_path_factory.mktemp("viewer") / "guided")
  subprocess.run(
      [sys.executable, "experiments/train.py", f"--workdir={workdir}",
       *GUIDED_SMOKE], cwd=ROOT, env=_env(), check=True,
      capture_output=True)
  return workdir


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _scene_region(run_dir: str, size: tuple[int, int], panel):
  """bool [H, W]: where the splats project from the viewer's start in a
  viewport of `size`, less the panel."""
  _, _, scene = run_lib.load_run(run_dir)
  position, look_at, up, fov = viewer.start_pose(scene)
  forward = (look_at - position) / np.linalg.norm(look_at - position)
  right = np.cross(forward, up)
  right /= np.linalg.norm(right)
  rotation = np.stack([right, np.cross(forward, right), forward])  # OpenCV
  means = np.asarray(ply.read_ply(
      os.path.join(run_dir, run_lib.POINT_CLOUD_PLY))[0].means)
  width, height = size
  x = (means - position) @ rotation.T
  x = x[x[:, 2] > 0.2]                     # in front of the near plane
  focal = 0.5 * height / np.tan(fov / 2)   # square pixels, vertical fov
  u = focal * x[:, 0] / x[:, 2] + width / 2
  v = focal * x[:, 1] / x[:, 2] + height / 2
  (u0, u1), (v0, v1) = (np.clip(np.percentile(a, [10, 90]), 0, n)
                        for a, n in ((u, width), (v, height)))
  region = np.zeros((height, width), bool)
  region[int(v0):int(v1), int(u0):int(u1)] = True
  px, py, pw, ph = panel
  region[max(py, 0):py + ph, max(px, 0):px + pw] = False
  return region


def _changed(a, b, region) -> float:
  """Fraction of `region` where two screenshots differ."""
  diff = np.abs(a.astype(int) - b.astype(int)).max(-1) > PIXEL_DIFFERENCE
  return float(diff[region].mean())


def _wait_changed(page, before, region, fraction):
  """The first screenshot whose `region` differs from `before` in more
  than `fraction` of its pixels, and that fraction."""
  end = time.monotonic() + WAIT_S
  while True:
    shot = page.screenshot()
    changed = _changed(shot, before, region)
    if changed > fraction or time.monotonic() > end:
      return shot, changed
    time.sleep(0.5)


def test_browser_shows_splats_and_s_j(guided_run, tmp_path):
  why = browser.missing()
  if why is not None:
    if _in_ci():
      pytest.fail(f"CI needs the browser: {why}")
    pytest.skip(f"{why}; under CI=1 this fails")
  port = _free_port()
  stderr = open(tmp_path / "viewer.stderr", "w+")
  proc = subprocess.Popen(
      [sys.executable, "experiments/view.py", f"--run={guided_run}",
       f"--port={port}"], cwd=ROOT, env=_env(), stdout=subprocess.PIPE,
      stderr=stderr, text=True)
  page = None
  try:
    page = browser.Browser()               # starts while the viewer does
    line = proc.stdout.readline()          # "" if the viewer ended
    if not line.startswith(viewer.READY_LINE):
      proc.wait()
      stderr.seek(0)
      pytest.fail(f"the viewer did not start: {line!r} {stderr.read()}")
    page.open(f"http://127.0.0.1:{port}/")
    page.wait_for_text("test (green)", WAIT_S)    # cameras: at view 0
    region = _scene_region(guided_run, page.viewport(),
                           page.rect(".mantine-Paper-root"))
    assert region.mean() > 0.1
    # The empty scene's background (frustums only), then the splats.
    page.click_label("Gaussians")
    time.sleep(1.0)
    empty = page.screenshot()
    page.click_label("Gaussians")
    splats, covered = _wait_changed(page, empty, region, MIN_SPLAT_FRACTION)
    assert covered > MIN_SPLAT_FRACTION, covered
    page.click_label("colour by s_j")
    scores, changed = _wait_changed(page, splats, region,
                                    MIN_TOGGLE_FRACTION)
    assert changed > MIN_TOGGLE_FRACTION, changed
    assert _changed(scores, empty, region) > MIN_SPLAT_FRACTION
    from PIL import Image  # pylint: disable=g-import-not-at-top
    shot = tmp_path / "viewer.png"
    Image.fromarray(splats).save(shot)
    kept = os.path.join(os.path.dirname(tmp_path), "viewer_screenshot.png")
    shutil.copy(shot, kept)
    print(f"viewer screenshot: {kept} (splats cover {covered:.0%} of the "
          f"scene's region; s_j colouring changes {changed:.0%})")
  finally:
    if page is not None:
      page.close()
    proc.send_signal(signal.SIGINT)             # Ctrl-C
    out, _ = proc.communicate(timeout=30)
    stderr.seek(0)
    err = stderr.read()
    stderr.close()
  assert proc.returncode == 0, err
  assert "viewer: stopped" in out and "Traceback" not in err, err


def test_viewer_panel_in_process(guided_run):
  """The click path and the prune preview, without a browser."""
  run = viewed_run.load(guided_run)
  assert run.stats is not None and len(run.pruned.centers) > 0
  scene = viewed_run.load_scene(run)
  server = viser.ViserServer(host="127.0.0.1", port=_free_port(),
                             verbose=False)
  try:
    view = viewer.Viewer([run, viewed_run.load(guided_run)], server)
    view.add_cameras(scene)
    masks = scene.train.masks
    index = int(np.argmax(masks.mean(axis=(1, 2))))
    view.selected = ("train", index)
    view._refresh_view()                 # pylint: disable=protected-access
    for name in ("photo", "render", "transient map", "ground-truth mask"):
      assert view.panel[name].visible, name
    # The scene is narrower than viewer.PANEL_WIDTH: shown at full size.
    np.testing.assert_array_equal(
        view.panel["ground-truth mask"].image[..., 0] > 127, masks[index])
    view.selected = ("test", 0)
    view._refresh_view()                 # pylint: disable=protected-access
    assert not view.panel["transient map"].visible
    # The tau slider recolours exactly the rows whose flag it changes.
    def flagged(tau):
      out = viewed_run.would_prune(run, tau)
      return ~np.bool_(out["refused"]) & (out["by_score"] | out["faint"])
    node, low_tau = view.nodes[0], 0.6 * run.cfg.pixel.tau_p
    view.highlight.value = True
    at_run_tau = node.rgbs.copy()
    view.tau.value = low_tau
    moved = flagged(low_tau) != flagged(run.cfg.pixel.tau_p)
    assert moved.sum() > 0
    np.testing.assert_array_equal(np.any(node.rgbs != at_run_tau, axis=1),
                                  moved)
    view.hide.value = True
    assert (node.opacities[flagged(low_tau)] == 0).all()
    view.hide.value = False
    view.drawn.value = 0.25                # the most opaque quarter
    opacities = np.sort(run.splats.opacities[:, 0])
    assert len(node.opacities) == int(np.ceil(0.25 * len(opacities)))
    assert node.opacities.min() >= np.floor(opacities[
        -len(node.opacities)] * 255) - 1      # stored as uint8
    view.run_choice.value = view.run_choice.options[1]
    assert view.nodes[1].visible and not view.nodes[0].visible
  finally:
    server.stop()


def test_residual_transient_map(guided_run):
  """A residual-map run shows the residual test of its final model's render
  at the threshold it ended with, as its whole-scene scorer gives it."""
  run = viewed_run.load(guided_run)
  # Without the alpha gate, so that a zero threshold masks every pixel.
  cfg = dataclasses.replace(
      run.cfg,
      semantic=dataclasses.replace(run.cfg.semantic, scorer="residual"),
      residual=dataclasses.replace(run.cfg.residual, min_alpha=0.0))
  scene = viewed_run.load_scene(run)
  index = 1
  photo = scene.train.images[index]
  res = np.asarray(residual.residual(
      viewed_run.render(run, scene, "train", index), photo))
  stats = residual.ResidualState.initial()
  run = dataclasses.replace(run, cfg=cfg, maps=stats.replace(
      threshold=np.float32(np.median(res))))
  shown = viewed_run.transient_map(run, scene, "train", index)
  expected = evaluation.view_map(
      run.params, np.ones(len(run.params.means), bool), run.maps,
      guidance.make_scorer(cfg, scene), scene.train, index, cfg,
      np.int32(run.degree))
  np.testing.assert_array_equal(shown, expected)
  assert 0.05 < shown.mean() < 0.95, shown.mean()
  everything = dataclasses.replace(run, maps=stats.replace(
      threshold=np.float32(0.0)))      # no residual is under 0
  assert viewed_run.transient_map(everything, scene, "train",
                                  index).min() == 1.0
  assert viewed_run.transient_map(run, scene, "test", 0) is None
  no_stats = dataclasses.replace(run, maps=None)   # a PLY-only run
  assert viewed_run.transient_map(no_stats, scene, "train", index) is None


def test_run_folder_keeps_what_the_viewer_needs(guided_run):
  pruned = viewed_run.load(guided_run).pruned
  events = {r["tag"] for r in summary.read(
      os.path.join(guided_run, run_lib.TENSORBOARD_DIR))}
  assert {"train/loss", "test/psnr", "mask/precision", "mask/recall",
          "semantic/s_j", "train_view/render",
          "train_view/transient_map"} <= events
  assert len(pruned.centers) > 0


def test_errors_are_one_line(guided_run, tmp_path):
  not_a_run = tmp_path / "empty"
  not_a_run.mkdir()
  with pytest.raises(ValueError) as e:
    viewed_run.load(str(not_a_run))
  assert "is not a run folder" in cli.error_line(e.value)
  bare = tmp_path / "bare"
  bare.mkdir()
  for name in (run_lib.RUN_JSON, run_lib.CONFIG_JSON):
    shutil.copy(os.path.join(guided_run, name), bare)
  with pytest.raises(FileNotFoundError) as e:
    viewed_run.load(str(bare))
  assert "neither checkpoint.npz nor point_cloud.ply" in str(e.value)
  with socket.socket() as held:
    held.bind(("127.0.0.1", 0))
    held.listen()
    port = held.getsockname()[1]
    proc = subprocess.run(
        [sys.executable, "experiments/view.py", f"--run={guided_run}",
         f"--port={port}"], cwd=ROOT, env=_env(), capture_output=True,
        text=True, timeout=120, check=False)
  lines = proc.stderr.strip().splitlines()
  assert proc.returncode == cli.EXIT_ERROR and len(lines) == 1, proc.stderr
  assert f"--port={port}" in lines[0] and "is in use" in lines[0]
