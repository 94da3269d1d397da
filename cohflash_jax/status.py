"""Per-pixel status codes: one enumeration, with messages, for every stage that judges a pixel.

Reconstruction writes them to `depth.h5` (`fit_status`), registration marks the pixels CCDs
2–4 do not see, calibration and the posteriors choose their pixels by them. The numbers are
part of the file formats (docs/formats.md): never renumber a code, only add new ones.
"""

from __future__ import annotations

import enum
import json


class Status(enum.IntEnum):
    """Why a pixel is not valid (0 = valid). When several reasons hold, the pipeline reports
    the most basic one (`reconstruct.policy.classify`)."""

    OK = 0
    LOW_SNR = 1
    NOT_CONVERGED = 2
    FIT_FAILED = 3
    BAD_DATA = 4
    SATURATED = 5
    DEAD = 6
    OUT_OF_RANGE = 7
    OUTSIDE_REGISTRATION = 8
    POOR_FIT = 9
    DC_EDGE = 10
    NOT_DETECTED = 11
    EDGE_BIAS = 12
    AMBIGUOUS = 13

    @property
    def message(self) -> str:
        """A short reason, as the summary and the depth file's `status_codes` give it."""
        return _MESSAGES[self]

    @classmethod
    def table(cls) -> dict[int, str]:
        """{code: message} for every status (the depth file's `status_codes` attribute)."""
        return {int(s): s.message for s in cls}

    @classmethod
    def table_json(cls) -> str:
        return json.dumps(cls.table())


_MESSAGES = {
    Status.OK: "ok",
    Status.LOW_SNR: "low_snr",
    Status.NOT_CONVERGED: "not_converged",
    Status.FIT_FAILED: "fit_failed",
    Status.BAD_DATA: "bad_data (NaN/inf)",
    Status.SATURATED: "saturated",
    Status.DEAD: "dead (constant)",
    Status.OUT_OF_RANGE: "out_of_range",
    Status.OUTSIDE_REGISTRATION: "outside_registration",
    Status.POOR_FIT: "poor_fit (reduced χ² above max_fit_chi2)",
    Status.DC_EDGE: "dc_edge (power rises towards DC: slow drift)",
    Status.NOT_DETECTED: "not_detected (no tone beyond what noise gives at the stated false-alarm rate)",
    Status.EDGE_BIAS: "edge_bias (a peak read-out near the window's ends, where the tone's mirror image biases it)",
    Status.AMBIGUOUS: "ambiguous (another depth the model predicts fits the frames nearly as well)",
}

# pixels whose data cannot carry a fit or a posterior: the noise model does not hold there
UNUSABLE_DATA = (Status.BAD_DATA, Status.SATURATED, Status.DEAD)
