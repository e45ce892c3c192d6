"""Layer 8: error measures and the scoring of tracked sequences against ground truth."""
