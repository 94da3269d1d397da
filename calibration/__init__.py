"""Calibration of real captures: four-CCD registration with Zhang's method (OpenCV).

Installed as `cohflash_calibration` so the install does not claim the generic top-level
name `calibration`. Modules: `board` (chessboard geometry), `registration` (detection,
intrinsics, stereo poses, pixel maps, XOR check, JSON, report), `synthetic` (a renderer of
chessboard views for four virtual CCDs with known cameras, for tests and studies).
"""
