"""What a calibration returns: the estimate with its uncertainties, the range noise and the dark squares'
bias it found, and a report per view (:class:`CalibrationResult`, written by
:mod:`~dem_graph.calibration.report`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dem_graph.calibration.board import BoardObservation


@dataclass(frozen=True)
class Tolerances:
    """How the returns on the board are found, metres (see :func:`tolerances`)."""

    margin_m: float  # beyond the outer squares' outline
    plane_m: float  # from the board's plane, once the estimate is refined
    first_plane_m: float  # from the board's plane under the first hypothesis; later selections never go wider
    hypothesis_m: float  # a hypothesis's segment counts as on its board within this RMS
    hypothesis_margin_m: float  # ... and beyond the outline by this much (a board's border is unknown)
    split_m: float  # a scan's run is split where it bends by more
    jump_m: float  # a run ends at a step larger than this (or five beam spacings per beam)
    gap_m: float  # a run goes on across missing returns spanning at most this


@dataclass
class ViewReport:
    """What became of one view."""

    index: int  # position among the recording's images, from 0
    name: str
    number: int | None = None  # the input's own number for the image (RGB31.png: 31); index + 1 when it has none
    used: bool = False
    reason: str = ""  # why the view was not used
    n_returns: int = 0  # laser returns on the board
    rms_mm: float | None = None  # point-to-plane RMS of those returns at the solution
    corner_rms_px: float | None = None  # board corners' reprojection RMS


@dataclass(frozen=True)
class RangeNoise:
    """The scanner's range noise: what the fit's residuals say (used), what the scans alone say, what was given."""

    sigma_m: float  # used: the fit's variance-component estimate (or the given value, when held)
    scans_sigma_m: float  # from the scans' second differences (NaN when too few)
    scans_samples: int
    given_sigma_m: float | None
    estimated: bool

    def warning(self, factor: float = 2.0) -> str | None:
        """A sentence when the given noise and the residuals disagree by more than ``factor``, else None."""
        if self.given_sigma_m is None or not self.estimated or self.given_sigma_m <= 0:
            return None
        ratio = self.given_sigma_m / self.sigma_m
        if 1.0 / factor <= ratio <= factor:
            return None
        return (
            f"the stated range noise {1000 * self.given_sigma_m:.1f} mm is {ratio:.1f} times the {1000 * self.sigma_m:.1f} mm "
            f"the residuals show: the estimate was used (hold the stated value with --fix-range-sigma)"
        )

    def summary(self) -> str:
        scans = "too few neighbouring returns" if not np.isfinite(self.scans_sigma_m) else f"{1000 * self.scans_sigma_m:.1f} mm"
        given = "" if self.given_sigma_m is None else f", given {1000 * self.given_sigma_m:.1f} mm"
        how = "estimated from the residuals" if self.estimated else "given and held"
        return f"range noise {1000 * self.sigma_m:.1f} mm ({how}; the scans' neighbouring returns say {scans}{given})"

    def to_dict(self) -> dict:
        return {
            "sigma_mm": 1000 * self.sigma_m,
            "source": "variance-component estimate from the fit's residuals" if self.estimated else "given, held",
            "scans_sigma_mm": None if not np.isfinite(self.scans_sigma_m) else 1000 * self.scans_sigma_m,
            "scans_samples": self.scans_samples,
            "given_sigma_mm": None if self.given_sigma_m is None else 1000 * self.given_sigma_m,
        }


@dataclass(frozen=True)
class DarkSquares:
    """Returns on dark squares and their range bias, when the images showed which squares are dark."""

    n_returns: int  # on dark squares, of the returns used
    n_total: int
    bias_m: float | None  # estimated and removed; None when not estimated
    bias_sigma_m: float | None
    views_with_colours: int  # views whose image showed which squares are dark

    def to_dict(self) -> dict:
        return {
            "returns_on_dark_squares": self.n_returns,
            "returns_used": self.n_total,
            "range_bias_mm": None if self.bias_m is None else 1000 * self.bias_m,
            "range_bias_sigma_mm": None if self.bias_sigma_m is None else 1000 * self.bias_sigma_m,
            "views_with_colours": self.views_with_colours,
        }

    def summary(self) -> str:
        if self.bias_m is None:
            why = "the images did not show which squares are dark" if self.views_with_colours == 0 else "too few returns on them"
            return f"dark squares: {self.n_returns} of {self.n_total} returns; range bias not estimated ({why})"
        return f"dark squares: {self.n_returns} of {self.n_total} returns, range bias {1000 * self.bias_m:+.1f} +- {1000 * self.bias_sigma_m:.1f} mm (estimated and removed)"


@dataclass
class CalibrationResult:
    T_cam_laser: np.ndarray
    covariance: np.ndarray  # 6x6 [rot, trans] of the right perturbation T_cam_laser * Exp(xi); rad^2, m^2
    T_initial: np.ndarray
    variance_factor: float
    views: list[ViewReport]
    on_board: dict[int, np.ndarray] = field(default_factory=dict)  # view -> beam indices on the board
    boards: dict[int, BoardObservation] = field(default_factory=dict)
    jackknife_covariance: np.ndarray | None = None  # leave-one-pose-out, same convention as covariance
    n_poses: int = 0  # distinct board poses among the views used
    noise: RangeNoise | None = None
    dark: DarkSquares | None = None
    model_sensitivity: np.ndarray | None = None  # (6,) largest move of [rot, trans] under other noise models (model_sensitivity)
    tolerances: Tolerances | None = None

    @property
    def rig_covariance(self) -> np.ndarray:
        """What the rig carries: the formal covariance, or the leave-one-pose-out one when that has more than
        three times the formal standard deviation on some axis (then the range errors are not white noise, as
        with the range bias real scanners show on dark squares). On white noise the leave-one-pose-out spread
        runs 1-1.8 times the formal one (simulated, 12 poses): the jackknife is conservative."""
        if self.jackknife_covariance is not None and np.any(np.diag(self.jackknife_covariance) > 9.0 * np.diag(self.covariance)):
            return self.jackknife_covariance
        return self.covariance

    @property
    def sigma_rot_deg(self) -> np.ndarray:
        return np.degrees(np.sqrt(np.diag(self.covariance)[:3]))

    def recording_advice(self, max_sigma_rot_deg: float = 0.1) -> str | None:
        """What to record next when the rotation the rig carries is known to worse than ``max_sigma_rot_deg``
        (1 sigma, about any laser axis; 0.1 deg keeps three sigma within 0.3 deg), else None. Tilting the board
        forward and back is what fixes the scan plane's tilt, turning it sideways its heading (docs/calibration.md,
        "Recording")."""
        sigma = np.degrees(np.sqrt(np.diag(self.rig_covariance)[:3]))
        worst = int(np.argmax(sigma))
        if sigma[worst] <= max_sigma_rot_deg:
            return None
        how = (
            "tilted 35-55 deg forward or back, held well to the left and right of the centre",  # the scan plane's roll
            "tilted 35-55 deg forward or back, 1.5-2 m away as well as near",  # its pitch: heights grow with distance
            "turned 20-40 deg to the left and to the right",  # the heading within the scan plane
        )[worst]
        return f"the rotation about the laser's {'xyz'[worst]} axis is known to {sigma[worst]:.2f} deg (1 sigma): record more views, with the board {how}"

    @property
    def sigma_trans_mm(self) -> np.ndarray:
        return 1000.0 * np.sqrt(np.diag(self.covariance)[3:])

    def to_dict(self) -> dict:
        used = [v for v in self.views if v.used]
        return {
            "T_cam_laser": self.T_cam_laser.tolist(),
            "covariance_rot_trans": self.covariance.tolist(),
            "covariance_convention": "right perturbation T_cam_laser * Exp([omega, v]), laser frame, gtsam order [rot, trans], rad^2 and m^2",
            "sigma_rot_deg": self.sigma_rot_deg.tolist(),
            "sigma_trans_mm": self.sigma_trans_mm.tolist(),
            "T_initial_closed_form": self.T_initial.tolist(),
            "range_noise": None if self.noise is None else self.noise.to_dict(),
            "model_sensitivity": None
            if self.model_sensitivity is None
            else {
                "what": "largest move of the estimate refined with the range noise halved, doubled, and without the dark squares' bias",
                "rot_deg": np.degrees(self.model_sensitivity[:3]).tolist(),
                "trans_mm": (1000.0 * self.model_sensitivity[3:]).tolist(),
            },
            "dark_squares": None if self.dark is None else self.dark.to_dict(),
            "tolerances_m": None if self.tolerances is None else dict(vars(self.tolerances)),
            "variance_factor": self.variance_factor,
            "distinct_poses": self.n_poses,
            "rig_covariance": "jackknife" if self.rig_covariance is self.jackknife_covariance else "formal",
            "jackknife": None
            if self.jackknife_covariance is None
            else {
                "what": "leave-one-pose-out spread of the estimate, same convention as covariance_rot_trans",
                "covariance_rot_trans": self.jackknife_covariance.tolist(),
                "sigma_rot_deg": np.degrees(np.sqrt(np.diag(self.jackknife_covariance)[:3])).tolist(),
                "sigma_trans_mm": (1000.0 * np.sqrt(np.diag(self.jackknife_covariance)[3:])).tolist(),
            },
            "views_used": len(used),
            "views_rejected": len(self.views) - len(used),
            "residual_rms_mm": float(np.sqrt(np.mean([v.rms_mm**2 for v in used]))) if used else None,
            "views": [
                {
                    "number": v.number if v.number is not None else v.index + 1,
                    "index": v.index,
                    "name": v.name,
                    "used": v.used,
                    **({"reason": v.reason} if not v.used else {}),
                    "n_returns": v.n_returns,
                    "rms_mm": v.rms_mm,
                    "corner_rms_px": v.corner_rms_px,
                }
                for v in self.views
            ],
        }
