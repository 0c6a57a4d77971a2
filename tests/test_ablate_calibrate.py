"""experiments/ablate.py and calibrate_tau.py: rows, flags, Otsu, plots."""

import os
import pathlib
import sys

from absl.testing import absltest
import numpy as np

_REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(_REPO / "experiments"))
import ablate  # pylint: disable=g-import-not-at-top,wrong-import-position
import calibrate_tau  # pylint: disable=g-import-not-at-top,wrong-import-position


def _metrics(psnr, *, alive=700, by_score=200, by_rule=100):
  return {"test": {"psnr": psnr, "ssim": 0.5, "lpips": 0.2,
                   "lpips_net": "alex"},
          "train_seconds": 10.0, "steps": 30, "num_gaussians": alive,
          "semantic": {"label": "CLIP-GS machinery, ORACLE scorer",
                       "fraction_pruned": (by_score + by_rule)
                       / (by_score + by_rule + alive),
                       "num_pruned_semantic": by_score,
                       "num_pruned_visibility": by_rule}}


class CalibrateTest(absltest.TestCase):

  def test_otsu_splits_two_modes(self):
    edges = np.linspace(0.0, 0.05, 51)
    hist = np.zeros(50)
    hist[8:12] = 100.0          # static mode around 0.01
    hist[40:44] = 20.0          # transient mode around 0.042
    tau = calibrate_tau.otsu_threshold(hist, edges)
    # Any edge in the empty gap [0.012, 0.040] separates; the middle one.
    self.assertAlmostEqual(tau, 0.026, delta=0.0015)

  def test_otsu_degenerate(self):
    edges = np.linspace(0.0, 1.0, 5)
    self.assertIsNone(calibrate_tau.otsu_threshold(np.zeros(4), edges))
    self.assertIsNone(calibrate_tau.otsu_threshold([0, 5, 0, 0], edges))

  def test_sweep_row_fractions(self):
    r = calibrate_tau.sweep_row(0.02, _metrics(21.0), None, 20.0)
    self.assertAlmostEqual(r["delta_psnr"], 1.0)
    self.assertAlmostEqual(r["fraction_pruned"], 0.3)
    self.assertAlmostEqual(r["fraction_pruned_by_score"], 0.2)
    self.assertAlmostEqual(r["fraction_pruned_by_rule"], 0.1)
    failed = calibrate_tau.sweep_row(0.3, None, "exit code 1", 20.0)
    self.assertEqual(failed["status"], "failed")
    text = calibrate_tau.format_markdown([r, failed], {"steps": 30})
    self.assertIn("| 0.02 | 21.00 | +1.00 |", text)
    self.assertIn("FAILED (exit code 1)", text)

  def test_histogram_plot(self):
    edges = np.linspace(0.0, 0.05, 51).tolist()
    event = lambda step, peak: {"step": step, "histogram": np.eye(50)[
        peak].tolist()}
    events = {0.02: {"histogram_edges": edges,
                     "events": [event(50, 10), event(90, 12)]},
              0.3: {"histogram_edges": edges, "events": [event(50, 10)]}}
    out = os.path.join(self.create_tempdir().full_path, "h.png")
    calibrate_tau.plot_histograms(events, out)
    self.assertGreater(os.path.getsize(out), 1000)
    with self.assertRaisesRegex(ValueError, "no run has a prune event"):
      calibrate_tau.plot_histograms({0.02: None}, out)


class AblateTest(absltest.TestCase):

  def test_row_flags(self):
    kw = dict(tau=0.03, weighting="contribution", clip_weights=None)
    reg = ablate.row_flags("oracle_reg_only", **kw)
    self.assertIn("--semantic=oracle", reg)
    self.assertIn("--nosemantic_prune", reg)
    self.assertIn("--tau=0.03", reg)
    self.assertIn("--lambda_c=0", ablate.row_flags("oracle_prune_only", **kw))
    self.assertIsNone(ablate.row_flags("clip_generic", **kw))
    generic = ablate.row_flags("clip_generic", tau=None,
                               weighting="visibility", clip_weights="w.npz")
    self.assertIn("--distractor_prompts=a photo of an object,a photo of a "
                  "thing", generic)
    self.assertIn("--clip_weights=w.npz", generic)

  def test_rows_and_markdown(self):
    rows = [ablate.ablation_row("vanilla", _metrics(20.0), None, 20.0, 23.0),
            ablate.ablation_row("oracle_reg_only", _metrics(21.5), None,
                                20.0, 23.0),
            ablate.ablation_row("clip_generic", None, None, 20.0, 23.0)]
    self.assertAlmostEqual(rows[1]["delta_psnr"], 1.5)
    self.assertAlmostEqual(rows[1]["gap_to_clean"], 1.5)
    self.assertEqual(rows[2]["status"], "not run")
    text = ablate.format_markdown(rows, {"steps": 30})
    self.assertIn("| ORACLE: opacity loss only | 21.50 | +1.50 | +1.50 |",
                  text)
    self.assertIn("| CLIP: generic prompts | not run: needs --clip_weights", text)
    self.assertIn("| vanilla 3DGS (clutter) | 20.00 | — | +3.00 |", text)


if __name__ == "__main__":
  absltest.main()
