"""Salient points (fingertips): detector network with Hough voting, training targets,
precision-recall evaluation (thesis Ch. 4.2, Eq. 4.14-4.15; Ballan et al. 2012, Sec. 4)."""

from torchhand.salient.detector import (DEFAULT_ONNX, DEFAULT_WEIGHTS, Detections, OnnxSalientDetector, SalientConfig,
                       SalientDetector, SalientNet, SalientOutput, detect_peaks, export_onnx, hough_votes,
                       normalise_depth)
from torchhand.salient.precision_recall import PRCurve, average_precision, match_detections

__all__ = ["DEFAULT_ONNX", "DEFAULT_WEIGHTS", "Detections", "OnnxSalientDetector", "SalientConfig",
           "SalientDetector", "SalientNet", "SalientOutput", "detect_peaks", "export_onnx", "hough_votes",
           "normalise_depth", "PRCurve", "average_precision", "match_detections"]
