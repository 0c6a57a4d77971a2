"""Per-pixel transient maps without an oracle: the residual test, ImageNet
feature regions and per-pixel features, the learned classifier, and the
sources a train step reads its map from."""
