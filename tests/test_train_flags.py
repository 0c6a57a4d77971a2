"""experiments/train.py rejects bad semantic flags with one clear line."""

import os
import pathlib
import subprocess
import sys

from absl.testing import absltest
from absl.testing import parameterized

ROOT = pathlib.Path(__file__).resolve().parents[1]


class SemanticFlagsTest(parameterized.TestCase):

  @parameterized.named_parameters(
      ("no_weights", ["--semantic=clip"], "CLIP weights are needed"),
      ("missing_weights", ["--semantic=clip",
                           "--clip_weights=/nonexistent/clip.pt"],
       "do not exist"),
      ("tau", ["--semantic=oracle", "--tau=2"], "tau=2.0 is not in [0, 1]"),
      ("cadence", ["--semantic=oracle", "--score_every=0"],
       "score_every=0 must be >= 1"),
      ("nothing_to_do", ["--semantic=oracle", "--lambda_c=0",
                         "--nosemantic_prune"], "leaves guidance nothing"),
      ("lambda_c", ["--semantic=oracle", "--lambda_c=-1"],
       "lambda_c=-1.0 must be >= 0"),
      ("no_prompts", ["--semantic=clip", "--distractor_prompts="],
       "no distractor prompts"),
      ("tau_p", ["--semantic=oracle", "--evidence=pixel", "--tau_p=2"],
       "tau_p=2.0 is not in [0, 1]"),
      ("masking_needs_pixels", ["--semantic=oracle", "--loss_masking"],
       "loss_masking needs evidence='pixel'"))
  def test_bad_flags(self, flags, message):
    env = dict(os.environ, PYTHONPATH=str(ROOT),
               CLIPGS_CLIP_WEIGHTS="")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "train.py"),
         f"--workdir={self.create_tempdir().full_path}", "--steps=1",
         *flags], capture_output=True, text=True, env=env, cwd=ROOT,
        check=False)
    self.assertNotEqual(proc.returncode, 0)
    self.assertIn(message, proc.stderr)
    self.assertNotIn("Traceback", proc.stderr)


if __name__ == "__main__":
  absltest.main()
