"""Salient points (fingertips on depth, nails on colour): detector network with Hough
voting, training targets, precision-recall evaluation (thesis Ch. 4.2, Eq. 4.14-4.15;
Ballan et al. 2012, Sec. 4)."""

from torchhand.salient.detector import (DEFAULT_NAIL_ONNX, DEFAULT_NAIL_WEIGHTS, DEFAULT_ONNX, DEFAULT_WEIGHTS,
                                        MODALITIES, OnnxSalientDetector, SalientConfig, SalientDetector, SalientNet,
                                        SalientOutput, export_onnx, normalise_colour, normalise_depth, shipped_weights)
from torchhand.salient.hough import Detections, detect_peaks, hough_votes
from torchhand.salient.precision_recall import PRCurve, average_precision, match_detections

__all__ = ["DEFAULT_NAIL_ONNX", "DEFAULT_NAIL_WEIGHTS", "DEFAULT_ONNX", "DEFAULT_WEIGHTS", "MODALITIES", "Detections",
           "OnnxSalientDetector", "SalientConfig", "SalientDetector", "SalientNet", "SalientOutput", "detect_peaks",
           "export_onnx", "hough_votes", "normalise_colour", "normalise_depth", "shipped_weights", "PRCurve",
           "average_precision", "match_detections"]
