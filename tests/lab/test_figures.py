"""clipgs_jax.figures: nearest view, PSNR, and the grid and curve PNGs."""

import json
import os

from absl.testing import absltest
import numpy as np

from clipgs_jax import camera
from clipgs_jax.lab import figures
from clipgs_jax.data import default_scene
from clipgs_jax.data import images
from clipgs_jax.data import scene as scene_lib

DOWNSCALE = 2           # the default scene's 128x96 views become 64x48


def _rot_z(angle):
  c, s = np.cos(angle), np.sin(angle)
  return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _cameras(centres, angles):
  """Stacked cameras at `centres` (world), rotated about z by `angles`."""
  rot = np.stack([_rot_z(a) for a in angles])
  trans = -np.einsum("vij,vj->vi", rot, np.asarray(centres, np.float64))
  ones = np.ones(len(angles))
  return camera.Camera(rotation=rot, translation=trans, fx=ones, fy=ones,
                       cx=ones, cy=ones, width=2, height=2)


class PiecesTest(absltest.TestCase):

  def test_nearest_train_view_by_centre(self):
    train = _cameras([[0, 0, 0], [1, 0, 0], [0, 5, 0], [3, 3, 0]],
                     [0.0, np.pi / 2, np.pi, -np.pi / 2])
    test = _cameras([[2.6, 2.4, 0]], [np.pi])
    centre = camera.camera_center(test)[0]
    # Centre (2.6, 2.4, 0) is nearest (3, 3, 0); the translations alone
    # (differently rotated centres) would pick view 0 instead.
    self.assertEqual(figures.nearest_train_view(centre, train), 3)
    naive = np.linalg.norm(train.translation - test.translation[0], axis=-1)
    self.assertEqual(int(np.argmin(naive)), 0)
    # camera_center works on stacked cameras too.
    np.testing.assert_allclose(camera.camera_center(train)[2], [0, 5, 0],
                               atol=1e-12)

  def test_view_psnr(self):
    a = np.zeros((2, 2, 3))
    # Every value off by 0.1: MSE 0.01, 20 dB.
    self.assertAlmostEqual(figures.view_psnr(a, a + 0.1), 20.0, places=6)
    # Half the pixels off by 0.2: MSE 0.02, 10 log10(50) = 16.9897 dB.
    b = a.copy()
    b[0] = 0.2
    self.assertAlmostEqual(figures.view_psnr(b, a), 16.98970004, places=6)
    self.assertEqual(figures.view_psnr(a, a), float("inf"))
    with self.assertRaisesRegex(ValueError, "shapes differ"):
      figures.view_psnr(a, np.zeros((2, 3, 3)))

  def test_pick_views(self):
    self.assertEqual(figures.pick_views(13, 3), [0, 6, 12])
    self.assertEqual(figures.pick_views(5, 2), [0, 4])
    self.assertEqual(figures.pick_views(2, 3), [0, 1])
    with self.assertRaises(ValueError):
      figures.pick_views(5, 0)


def _write_row(root, row, renders=None, curve=True, downscale=DOWNSCALE):
  """A fake table.py row folder: run.json, curve.json, renders/test."""
  folder = os.path.join(root, row)
  os.makedirs(folder)
  with open(os.path.join(folder, "run.json"), "w") as f:
    json.dump({"downscale": downscale}, f)
  if curve:
    with open(os.path.join(folder, "curve.json"), "w") as f:
      json.dump([{"step": s, "seconds": s / 10, "test_psnr": 15 + s / 100}
                 for s in (0, 100, 200)], f)
  for name, image in (renders or {}).items():
    images.write_png(os.path.join(folder, "renders", "test", name), image,
                     bits=16)


class FiguresTest(absltest.TestCase):

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    cls.bench = default_scene.ensure_default_scene()
    cls.test = scene_lib.load_scene(cls.bench, downscale=DOWNSCALE).test

  def _workroot(self):
    root = self.create_tempdir().full_path
    runs = os.path.join(root, os.path.basename(self.bench))
    names = self.test.names
    grey = np.full(self.test.images.shape[1:], 0.5, np.float32)
    # vanilla: flat grey; oracle: the ground truth itself (16-bit, exact);
    # clean: a folder without renders (its column must be left out).
    _write_row(runs, "vanilla", {n: grey for n in names})
    _write_row(runs, "oracle", dict(zip(names, self.test.images)))
    _write_row(runs, "clean", curve=False)
    return root, runs

  def test_grid_and_curve(self):
    root, runs = self._workroot()
    out = self.create_tempdir().full_path
    grid = os.path.join(out, "g.png")
    with self.assertLogs(level="WARNING") as logs:
      summary = figures.make_grid(self.bench, runs, grid, views=2)
    self.assertTrue(any("renders/test" in l for l in logs.output))
    self.assertEqual(summary["rows"], ["vanilla", "oracle"])
    self.assertEqual(summary["titles"], [
        figures.INPUT_TITLE, "vanilla 3DGS", "CLIP-GS (ORACLE scorer)",
        "ground truth"])
    names = self.test.names
    self.assertEqual([v["test"] for v in summary["views"]],
                     [names[0], names[-1]])
    grey = images.read_image(
        os.path.join(runs, "vanilla", "renders", "test", names[0]))
    for k, v in enumerate(summary["views"]):
      i = names.index(v["test"])
      self.assertStartsWith(v["input"], "2clutter")
      self.assertEqual(v["psnr"]["oracle"], float("inf"))
      mse = np.mean((grey.astype(np.float64) - self.test.images[i]) ** 2)
      self.assertAlmostEqual(v["psnr"]["vanilla"], -10 * np.log10(mse),
                             places=4, msg=k)
    # Figure size: 2.4 in per panel width, 2.4 h / w + 0.6 in per row.
    pixels = images.read_image(grid)
    h, w = self.test.images.shape[1:3]
    want = 4 * 2.4 / (2 * (2.4 * h / w + 0.6))
    self.assertAlmostEqual(pixels.shape[1] / pixels.shape[0], want, places=2)
    self.assertGreater(pixels.std(), 0.01)

    curve = os.path.join(out, "c.png")
    self.assertEqual(figures.make_curve(runs, curve), ["vanilla", "oracle"])
    self.assertGreater(os.path.getsize(curve), 1000)

    written = figures.make_figures([self.bench], root, out, views=1)
    scene = os.path.basename(self.bench)
    self.assertEqual(written, [os.path.join(out, f"{scene}_grid.png"),
                               os.path.join(out, f"{scene}_curve.png")])
    self.assertTrue(all(os.path.getsize(p) > 0 for p in written))

  def test_errors(self):
    empty = self.create_tempdir().full_path
    with self.assertRaisesRegex(ValueError, "no row folder.*" + empty):
      figures.make_grid(self.bench, empty, os.path.join(empty, "g.png"))
    _, runs = self._workroot()
    # Renders at downscale 2 do not match the views at downscale 4.
    with self.assertRaisesRegex(ValueError, "--figure_downscale"):
      figures.make_grid(self.bench, runs, os.path.join(empty, "g.png"),
                        views=1, downscale=4)
    _write_row(runs, "clip", downscale=4)
    with self.assertRaisesRegex(ValueError, "differ in downscale"):
      figures.runs_downscale(runs, figures.present_rows(runs))
    self.assertFalse(os.path.exists(os.path.join(empty, "g.png")))
    with self.assertRaisesRegex(FileNotFoundError, "nope is not a folder"):
      figures.make_figures([os.path.join(empty, "nope")], empty, empty)


if __name__ == "__main__":
  absltest.main()
