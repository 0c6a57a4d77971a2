"""experiments/table.py: row collection, Markdown, and an end-to-end run."""

import json
import os
import pathlib
import subprocess
import sys
import time

from absl.testing import absltest

from clipgs_jax.data import default_scene

_REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(_REPO / "experiments"))
import table  # pylint: disable=g-import-not-at-top,wrong-import-position


def _metrics(psnr, *, fraction_pruned=None, label=None, num=1000):
  """A hand-made train.py metrics.json dict."""
  m = {"test": {"psnr": psnr, "ssim": 0.5, "lpips": 0.25,
                "lpips_net": "alex"},
       "train_seconds": 12.0, "steps": 30, "num_gaussians": num}
  if fraction_pruned is not None:
    m["semantic"] = {"label": label, "fraction_pruned": fraction_pruned}
  return m


class FormatTest(absltest.TestCase):

  def _rows(self):
    oracle_label = ("CLIP-GS machinery, ORACLE scorer (ground-truth masks, "
                    "not CLIP)")
    return table.add_deltas([
        table.collect_row("s", "vanilla", _metrics(20.0)),
        table.collect_row("s", "oracle", _metrics(
            21.5, fraction_pruned=0.125, label=oracle_label, num=900)),
        table.collect_row("s", "clip", None, "exit code 3"),
        table.collect_row("s", "clean", _metrics(24.0)),
    ])

  def test_collect_and_deltas(self):
    rows = {r["row"]: r for r in self._rows()}
    self.assertIn("ORACLE", rows["oracle"]["method"])
    # Oracle: 21.5 - 20.0 = +1.5 over vanilla, 24.0 - 21.5 = 2.5 below clean.
    self.assertAlmostEqual(rows["oracle"]["delta_psnr"], 1.5)
    self.assertAlmostEqual(rows["oracle"]["gap_to_clean"], 2.5)
    self.assertAlmostEqual(rows["oracle"]["fraction_pruned"], 0.125)
    self.assertIsNone(rows["vanilla"]["delta_psnr"])
    self.assertAlmostEqual(rows["vanilla"]["gap_to_clean"], 4.0)
    self.assertIsNone(rows["vanilla"]["fraction_pruned"])
    self.assertEqual(rows["clip"]["status"], "failed")
    self.assertIsNone(rows["clip"]["delta_psnr"])
    self.assertEqual(rows["clean"]["status"], "ok")

  def test_oracle_label_forced_and_nan(self):
    m = _metrics(float("nan"), fraction_pruned=1.0, label="something")
    r = table.collect_row("s", "oracle", m)
    self.assertIn("ORACLE", r["method"])
    self.assertIsNone(r["psnr"])  # Non-finite: None, so JSON stays valid.
    json.dumps(r, allow_nan=False)

  def test_markdown(self):
    text = table.format_markdown(self._rows(), {"steps": 30,
                                                "lpips_net": "alex"})
    self.assertIn("- steps: 30", text)
    self.assertIn("LPIPS (alex)", text)
    body = [l for l in text.splitlines() if l.startswith("| s |")]
    self.assertLen(body, 4)
    vanilla, oracle, clip, clean = body
    self.assertIn("ORACLE", oracle)
    self.assertIn("| 21.50 |", oracle)
    self.assertIn("| 0.125 | n/a | +1.50 | +2.50 |", oracle)
    self.assertIn("| — | — | — | +4.00 |", vanilla)
    self.assertIn("FAILED (exit code 3)", clip)
    self.assertIn("| 24.00 |", clean)
    self.assertTrue(clean.endswith("| — | — | — | — |"), clean)

  def test_row_flags(self):
    pixel = ["oracle_pixel", "oracle_pixel_masked"]
    self.assertEqual(table.row_names(None),
                     ["vanilla", "oracle", *pixel, "clean"])
    self.assertEqual(table.row_names("w.npz"),
                     ["vanilla", "oracle", *pixel, "clip", "clip_pixel",
                      "clean"])
    self.assertEqual(table.row_names(None, ["clean", "oracle_pixel"]),
                     ["oracle_pixel", "clean"])
    with self.assertRaisesRegex(ValueError, "unknown rows"):
      table.row_names(None, ["bogus"])
    masked = table.row_flags("oracle_pixel_masked", tau=0.1,
                             weighting="contribution", clip_weights=None)
    self.assertIn("--evidence=pixel", masked)
    self.assertIn("--loss_masking", masked)
    self.assertNotIn("--tau=0.1", masked)
    self.assertEqual(
        table.row_flags("clean", tau=0.1, weighting="contribution",
                        clip_weights=None),
        ["--train_split=clean", "--semantic=off"])
    clip = table.row_flags("clip", tau=0.1, weighting="contribution",
                           clip_weights="w.npz")
    self.assertIn("--semantic=clip", clip)
    self.assertIn("--scale_semantic_schedule", clip)
    self.assertIn("--tau=0.1", clip)
    self.assertIn("--clip_weights=w.npz", clip)


class EndToEndTest(absltest.TestCase):

  def _run(self, scene, root):
    env = dict(os.environ, JAX_PLATFORMS="cpu",
               # Compile time dominates these 10-step rows.
               JAX_DISABLE_MOST_OPTIMIZATIONS="1")
    cmd = [sys.executable, str(_REPO / "experiments" / "table.py"),
           f"--benchmarks={scene}", f"--workroot={root}", "--steps=10",
           "--downscale=4", "--extra_flags=--preset=smoke --curve_points=1",
           "--rows=vanilla,oracle_pixel,clean"]
    start = time.monotonic()
    proc = subprocess.run(cmd, cwd=_REPO, env=env, capture_output=True,
                          text=True, check=False)
    self.assertEqual(proc.returncode, 0, proc.stderr[-3000:])
    return proc, time.monotonic() - start

  def test_three_rows_then_all_skipped(self):
    scene = default_scene.ensure_default_scene()
    root = self.create_tempdir().full_path
    self._run(scene, root)
    with open(os.path.join(root, "table.json")) as f:
      out = json.load(f)
    rows = out["rows"]
    self.assertEqual([r["row"] for r in rows],
                     ["vanilla", "oracle_pixel", "clean"])
    for r in rows:
      self.assertEqual(r["status"], "ok", r)
      self.assertEqual(r["steps"], 10)
      self.assertIsInstance(r["psnr"], float)
      self.assertGreater(r["train_seconds"], 0.0)
    self.assertIsNotNone(rows[1]["fraction_pruned"])
    self.assertIsNotNone(rows[1]["delta_psnr"])
    self.assertEqual(out["settings"]["steps"], 10)
    text = pathlib.Path(root, "table.md").read_text()
    self.assertIn("ORACLE", text)
    self.assertLen([l for l in text.splitlines()
                    if l.startswith(f"| {os.path.basename(scene)} |")], 3)

    proc, seconds = self._run(scene, root)
    self.assertEqual(proc.stderr.count("skip "), 3, proc.stderr[-3000:])
    self.assertLess(seconds, 30.0)  # No training the second time.


if __name__ == "__main__":
  absltest.main()
