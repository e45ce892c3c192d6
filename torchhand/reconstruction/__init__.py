"""Reconstruction from depth: in-hand scanning of objects (thesis Ch. 5)."""
