"""Calibration of real captures (four-CCD registration, hybrid calibration).

Installed as `cohflash_calibration` so the install does not claim the generic top-level
name `calibration`. Nothing is implemented here yet: see the open registration and
hybrid-calibration issues.
"""
