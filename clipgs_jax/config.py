"""Frozen configuration dataclasses with the paper's and 3DGS's defaults."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class RenderConfig:
  """How the tile rasterizer projects, bins and blends.

  Choosing `tile_budget`: it must exceed the largest number of Gaussians that
  overlap one 16x16 tile, or the farthest ones in that tile are dropped (and
  counted in `RenderOutput.num_overflow`, never silently). Render a typical
  view once and read `max_tile_count`; then set the budget to the next power
  of two above it. Memory and time do not scale with the budget: each tile
  walks its depth-sorted list `chunk_size` entries at a time and stops when
  its pixels saturate or its list ends. The intersection buffer holds
  num_tiles * tile_budget entries (4 bytes each), which is what the budget
  costs.
  """
  near: float = 0.2            # near plane in scene units; closer is culled
  tile_budget: int = 2048      # K: max depth-sorted Gaussians per tile
  chunk_size: int = 32         # B: list entries blended per step per tile
