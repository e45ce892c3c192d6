"""Sequences on disk, synthetic RGB-D, sensor noise and torch Datasets."""
