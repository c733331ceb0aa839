"""Training layer: scenes, the training harness, PRDP-against-full comparisons and their plots."""
