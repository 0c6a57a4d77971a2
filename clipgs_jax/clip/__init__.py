"""CLIP towers in Flax: tokenizer, model, weight import and preprocessing."""
