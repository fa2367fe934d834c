"""Calibration maneuvers and fits that produce the versioned calibration file."""
