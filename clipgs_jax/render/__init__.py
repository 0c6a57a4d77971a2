"""The tile rasterizer: EWA projection, tile binning and depth sort, alpha
blending with its analytic backward."""
