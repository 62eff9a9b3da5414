"""One participant: calibrated limits (profiles), the calibration procedure, regions of the pad, and the
mapping from application electrodes to wired channels."""
