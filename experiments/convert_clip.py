"""Converts a CLIP checkpoint to the flat .npz that loads without torch.

  python experiments/convert_clip.py --src=ViT-B-32.pt --dst=vit_b32.npz
  python experiments/convert_clip.py --src=clip-vit-base-patch32/ \
      --dst=vit_b32.npz

--src may be OpenAI's TorchScript .pt (needs torch), a torch.save'd state
dict, a Hugging Face model.safetensors or the directory holding it, or one
of our .npz files. The variant is inferred from the tensor shapes unless
--variant names it; every missing or mis-shaped tensor is reported at once.
"""

import json

from absl import flags
import jax

from clipgs_jax import cli
from clipgs_jax.clip import model
from clipgs_jax.clip import weights

_SRC = flags.DEFINE_string(
    'src', None, 'CLIP checkpoint: .pt/.pth/.bin, .safetensors, a Hugging '
    'Face model directory, or .npz.')
_DST = flags.DEFINE_string(
    'dst', None, 'Output .npz; written to a temporary file in the same '
    'directory, then renamed over this path.')
_VARIANT = flags.DEFINE_enum(
    'variant', None, list(model.VARIANTS),
    'Expected variant; default: inferred from the tensor shapes.')
flags.mark_flags_as_required(['src', 'dst'])


def main(argv):
  cli.no_arguments(argv)
  config, params = weights.load(_SRC.value, _VARIANT.value)
  weights.save_npz(_DST.value, config, params)
  print(json.dumps({
      'src': _SRC.value,
      'dst': _DST.value,
      'variant': model.variant_name(config),
      'num_params': sum(x.size for x in jax.tree.leaves(params)),
  }))


if __name__ == '__main__':
  cli.run(main)
