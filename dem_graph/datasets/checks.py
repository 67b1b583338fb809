"""Checks of what a log holds, shared by the dataset readers: bad input refused in one line, faults survived.

A reader refuses (:class:`~dem_graph.errors.DatasetError` naming the file, the line or index, and
the problem) what no run can use:

- a clock fault: a time in a sensor stream more than :attr:`InputChecks.max_gap_s` after the one
  before it (or after the log's start). A robot's sensors do not fall silent for that long in a
  log that goes on; a clock that jumped would stretch the map over empty time. The reader does not
  guess where the log should be cut: the message names the line, the user fixes or cuts the log;
- an odometry covariance that is not one: not finite, not symmetric, a negative variance, not
  positive definite;
- an image of another size than the rig's camera.

It repairs, skips or marks, with one logged warning, what a run can go on without:

- an all-zero odometry covariance (ROS's "unknown"): replaced by the rig's odometry noise model for
  that increment's length (:meth:`~dem_graph.geometry.rig.OdometrySpec.covariance_of`);
- an odometry increment faster than the vehicle can move (:attr:`InputChecks.max_speed_mps`,
  :attr:`InputChecks.max_rotation_rate_rad_s`): skipped; the estimators' odometry integration
  bridges its time at the last increment's rate (:mod:`dem_graph.estimators.odometry`);
- a camera frame without texture (grey-level standard deviation below
  :attr:`InputChecks.min_image_std_dn`): marked ``CameraFrame.textureless``, for the estimator to
  predict its pose and track nothing in it;
- a camera frame bit-identical to the one before (a frozen camera driver repeating its last image):
  marked ``textureless`` the same way. No threshold: a live sensor's noise never repeats every
  pixel, so only a stale image does (a frame without texture is told as such, not as frozen);
- a log with no laser scan, or whose scans hold no valid return (every range NaN or outside the
  rig's range limits; when most finite ranges lie beyond ``laser.range_max_m``, perhaps a wrong
  unit): said when it is opened.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.datasets.events import CameraFrame
from dem_graph.errors import DatasetError
from dem_graph.geometry.rig import CameraSpec, LaserSpec, OdometrySpec

log = logging.getLogger(__name__)

SYMMETRY_RTOL = 1e-6
"""A covariance is symmetric when no entry differs from its mirror by more than this part of its largest entry."""

_AXES = ("rotation x", "rotation y", "rotation z", "translation x", "translation y", "translation z")  # gtsam order


class InputChecks(StrictModel):
    """The limits a log's readers hold it to, with defaults a field robot fits."""

    max_gap_s: float = Field(
        10.0,
        gt=0,
        description="a sensor's time stamp more than this after the one before it (or after the log's start) is a clock fault: the log is refused, seconds",
    )
    max_speed_mps: float = Field(
        10.0, gt=0, description="an odometry increment faster than this is skipped (bridged at the last increment's rate), m/s"
    )
    max_rotation_rate_rad_s: float = Field(
        2.0, gt=0, description="an odometry increment turning faster than this (its whole rotation angle over its time) is skipped, rad/s"
    )
    min_image_std_dn: float = Field(
        2.0,
        ge=0,
        description="a camera frame whose grey levels' standard deviation is below this has no texture: marked, not tracked, grey levels (0-255)",
    )
    max_skipped_fraction: float = Field(
        0.2,
        gt=0,
        le=1,
        description="a stream whose messages a reader skips (not finite, stamp not after its predecessor's, wrong shape) in a larger share than this is refused: a faulty driver, not a blemish, fraction of the stream's messages",
    )
    max_reordered_run: int = Field(
        5,
        ge=1,
        description="more consecutive messages of a stream than this whose stamps are not after the last one kept: the stream's clock went back as a whole (a clock fault), refused, messages",
    )


# ----------------------------------------------------------------------------------------------
# time stamps


def first_time_jump(t_s: np.ndarray, t_start_s: float | None, max_gap_s: float) -> int | None:
    """The first index whose time is more than ``max_gap_s`` after the one before it (index 0: after
    ``t_start_s``, unless None), or None."""
    t_s = np.asarray(t_s, dtype=float)
    if len(t_s) == 0:
        return None
    before_s = np.concatenate([[t_s[0] if t_start_s is None else t_start_s], t_s[:-1]])
    jumps = np.flatnonzero(t_s - before_s > max_gap_s)
    return int(jumps[0]) if len(jumps) else None


def time_text(t_s: float) -> str:
    """A time in seconds as people read it, with its unit: to the nanosecond, trailing zeros dropped
    ("100.213 s", "0.0 s"); never a library's repr (``np.float64(0.21300000000000002)``)."""
    text = f"{float(t_s):.9f}".rstrip("0")
    return f"{text}0 s" if text.endswith(".") else f"{text} s"


def check_time_jumps(where: str | Path, t_s: np.ndarray, t_start_s: float | None, checks: InputChecks, label: Callable[[int], str]) -> None:
    """Refuse a clock fault in one stream: a :class:`DatasetError` at ``where`` naming the item
    (``label(i)``, e.g. "line 42: t_s") whose time jumps more than ``checks.max_gap_s`` forward from
    the one before (the first: from ``t_start_s``, unless None)."""
    i = first_time_jump(t_s, t_start_s, checks.max_gap_s)
    if i is None:
        return
    before_s, before = (float(t_s[i - 1]), "the one before") if i else (float(t_start_s), "the log's start")
    raise DatasetError(
        where,
        f"{label(i)} = {time_text(t_s[i])} is {float(t_s[i]) - before_s:.3f} s after {before} ({time_text(before_s)}), more than "
        f"input_checks.max_gap_s = {checks.max_gap_s:g} s: a clock fault (correct the time stamps, or cut the log there)",
    )


def increasing_stamps(t_s: np.ndarray) -> np.ndarray:
    """Mask of the messages to keep so that the stamps ``t_s`` (n,) increase strictly: the longest
    strictly increasing subsequence, the earlier message kept where two would do (a duplicate stamp
    drops the second; a stamp that jumps ahead of its neighbours for one message drops that one)."""
    t = np.asarray(t_s, dtype=float)
    n = len(t)
    keep = np.zeros(n, dtype=bool)
    if n == 0:
        return keep
    # on the stamps reversed and negated, the patience sort's tie-breaking keeps the earlier messages
    s = -t[::-1]
    tails_value: list[float] = []
    tails_index: list[int] = []
    parent = np.full(n, -1)
    for k, v in enumerate(s):
        pos = int(np.searchsorted(tails_value, v, side="left"))
        parent[k] = tails_index[pos - 1] if pos else -1
        if pos == len(tails_value):
            tails_value.append(v)
            tails_index.append(k)
        else:
            tails_value[pos], tails_index[pos] = v, k
    k = tails_index[-1]
    while k >= 0:
        keep[n - 1 - k] = True
        k = parent[k]
    return keep


NONFINITE, STAMP_NOT_AFTER, WRONG_SHAPE = "nonfinite", "stamp_not_after", "wrong_shape"
_SKIP_KINDS = {
    NONFINITE: "hold a value that is not finite",
    STAMP_NOT_AFTER: "have a stamp not after the previous one's (a duplicate, or delivered late)",
    WRONG_SHAPE: "do not have the stream's shape",
}


_KIND_LABELS = {NONFINITE: "not finite", STAMP_NOT_AFTER: "stamp not after the previous", WRONG_SHAPE: "of another shape"}


class SkippedMessages:
    """The messages of one stream a reader skips, by kind (:data:`NONFINITE`, :data:`STAMP_NOT_AFTER`,
    :data:`WRONG_SHAPE`): one bad message costs one message. :meth:`finish` warns once per kind and
    refuses the stream when too many are bad (:attr:`InputChecks.max_skipped_fraction`) or when the
    stamps go back for a run of messages (:attr:`InputChecks.max_reordered_run`: the clock jumped)."""

    def __init__(self, where: str | Path, stream: str, item: str = "message", first_number: int = 0):
        """``item``: what the stream's entries are called in the messages ("message", "line"), numbered from ``first_number``."""
        self.where, self.stream = where, stream
        self.item, self.first_number = item, first_number
        self.first: dict[str, tuple[int, str]] = {}  # kind -> (message index, why) of the first skipped
        self.indices: dict[str, list[int]] = {}

    def skip(self, index: int, kind: str, why: str) -> None:
        """Skip message ``index`` for ``kind``; ``why``: what is wrong with it, for people (numbers with units)."""
        if int(index) in self.indices.get(kind, ()):
            return  # told already (a log replayed again)
        self.first.setdefault(kind, (int(index), why))
        self.indices.setdefault(kind, []).append(int(index))

    @property
    def skipped(self) -> set[int]:
        return {i for v in self.indices.values() for i in v}

    def counts(self) -> dict[str, int]:
        """``{"<stream>_<kind>": count}`` of the kinds skipped (the counters ``metrics.json`` keeps)."""
        return {f"{self.stream}_{kind}": len(v) for kind, v in self.indices.items()}

    def finish(self, n_messages: int, checks: InputChecks) -> None:
        """Refuse the stream (a :class:`DatasetError` in one line) or warn once per kind skipped."""
        self._check_reordered_run(checks)
        n_skipped = len(self.skipped)
        if n_messages and n_skipped > checks.max_skipped_fraction * n_messages:
            kinds = ", ".join(f"{len(v)} {_KIND_LABELS[kind]}" for kind, v in self.indices.items())
            i, why = min(self.first.values())
            first = f"{self.item} {i + self.first_number}"
            if n_skipped == n_messages:
                raise DatasetError(self.where, f"none of the {n_messages} {self.item}s can be used ({kinds}; first: {first}, {why})")
            raise DatasetError(
                self.where,
                f"{n_skipped} of {n_messages} {self.item}s cannot be used ({kinds}; first: {first}, {why}): more than "
                f"input_checks.max_skipped_fraction = {checks.max_skipped_fraction:.0%} of the stream, a faulty driver or recording rather than a blemish",
            )
        for kind, v in self.indices.items():
            i, why = self.first[kind]
            log.warning("%s: %d of %d %ss %s (first: %s %d, %s): skipped", self.where, len(v), n_messages, self.item, _SKIP_KINDS[kind], self.item, i + self.first_number, why)

    def _check_reordered_run(self, checks: InputChecks) -> None:
        """Refuse when more than ``checks.max_reordered_run`` consecutive messages were skipped for their stamps."""
        order = sorted(self.indices.get(STAMP_NOT_AFTER, []))
        start = 0
        for k in range(1, len(order) + 1):
            if k == len(order) or order[k] != order[k - 1] + 1:
                if k - start > checks.max_reordered_run:
                    raise DatasetError(
                        self.where,
                        f"{self.item}s {order[start] + self.first_number} to {order[k - 1] + self.first_number} ({k - start} in a row) have stamps not after the {self.item}s before them "
                        f"(more than input_checks.max_reordered_run = {checks.max_reordered_run}): the stream's clock went back, a clock fault "
                        "(correct the time stamps, or cut the log there)",
                    )
                start = k


# ----------------------------------------------------------------------------------------------
# odometry covariances


def unknown_covariances(covariance: np.ndarray) -> np.ndarray:
    """Mask of the (n,6,6) covariances that are all zero: ROS's convention for "unknown"."""
    return ~np.any(np.asarray(covariance) != 0.0, axis=(1, 2))


def covariance_problems(covariance: np.ndarray) -> tuple[int, str, int] | None:
    """The first of the (n,6,6) matrices that is not a covariance, why, and how many are not; None
    when all are. Each must be finite, symmetric (to :data:`SYMMETRY_RTOL` of its largest entry),
    with no negative variance, and positive definite."""
    C = np.asarray(covariance, dtype=float).reshape(-1, 6, 6)
    finite = np.all(np.isfinite(C), axis=(1, 2))
    C = np.where(finite[:, None, None], C, 0.0)  # the other checks read finite numbers
    scale = np.max(np.abs(C), axis=(1, 2))
    asymmetry = np.max(np.abs(C - np.swapaxes(C, 1, 2)), axis=(1, 2))
    symmetric = asymmetry <= SYMMETRY_RTOL * scale
    variances = np.diagonal(C, axis1=1, axis2=2)
    negative = np.any(variances < 0, axis=1)
    smallest = np.linalg.eigvalsh(0.5 * (C + np.swapaxes(C, 1, 2)))[:, 0] if len(C) else np.zeros(0)

    def asymmetric(i: int) -> str:
        return (
            f"is not symmetric (entries differ from their mirror by up to {asymmetry[i]:.3g}, {asymmetry[i] / scale[i]:.2g} of the largest)"
        )

    def negative_variance(i: int) -> str:
        k = int(np.argmin(variances[i]))
        return f"has a negative variance: {_AXES[k]} [{k},{k}] = {float(variances[i, k])!r}"

    faults = [  # in the order they are told
        (~finite, lambda i: "contains NaN or infinite values"),
        (finite & ~symmetric, asymmetric),
        (finite & symmetric & negative, negative_variance),
        (
            finite & symmetric & ~negative & ~(smallest > 0),
            lambda i: f"is not positive definite (smallest eigenvalue {float(smallest[i]):.3g})",
        ),
    ]
    bad = np.any([mask for mask, _ in faults], axis=0) if len(C) else np.zeros(0, dtype=bool)
    if not bad.any():
        return None
    first = int(np.argmax(bad))
    tell = next(tell for mask, tell in faults if mask[first])
    return first, tell(first), int(bad.sum())


def check_covariances(where: str | Path, covariance: np.ndarray, name: str = "covariance") -> None:
    """Refuse an odometry covariance that is not one (:func:`covariance_problems`); all-zero ones
    (unknown) pass, for :func:`repair_unknown_covariances`. A :class:`DatasetError` at ``where``
    naming ``name[index]`` and the problem."""
    known = np.flatnonzero(~unknown_covariances(covariance))
    found = covariance_problems(covariance[known])
    if found is not None:
        i, problem, _ = found
        raise DatasetError(where, f"{name}[{int(known[i])}] {problem}")


def repair_unknown_covariances(where: str | Path, covariance: np.ndarray, T_prev_curr: np.ndarray, spec: OdometrySpec | None) -> np.ndarray:
    """``covariance`` with each all-zero (unknown) one replaced by ``spec``'s noise model for that
    increment's length (the default model when the rig has none); one warning says how many."""
    unknown = np.flatnonzero(unknown_covariances(covariance))
    if len(unknown) == 0:
        return covariance
    model = spec if spec is not None else OdometrySpec()
    repaired = covariance.copy()
    for i in unknown:
        repaired[i] = model.covariance_of(T_prev_curr[i])
    log.warning(
        "%s: %d of %d odometry covariances are all zero (unknown, as in ROS; first: index %d): replaced by %s for each increment's length",
        where,
        len(unknown),
        len(covariance),
        int(unknown[0]),
        "the rig's odometry noise model" if spec is not None else "the default odometry noise model (the rig has no odometry block)",
    )
    return repaired


# ----------------------------------------------------------------------------------------------
# odometry motion


def rotation_angle_rad(R: np.ndarray) -> np.ndarray:
    """The rotation angle (n,) of rotations (n,3,3), 0 to pi."""
    return np.arccos(np.clip((np.einsum("nii->n", R) - 1.0) / 2.0, -1.0, 1.0))


def increment_rates(T_prev_curr: np.ndarray, dt_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Speed (m/s) and rotation rate (rad/s) of each increment (n,4,4) over its time ``dt_s`` (n,);
    an increment that moves in no time is infinitely fast."""
    T = np.asarray(T_prev_curr, dtype=float).reshape(-1, 4, 4)
    dt_s = np.asarray(dt_s, dtype=float)
    distance_m = np.linalg.norm(T[:, :3, 3], axis=1)
    angle_rad = rotation_angle_rad(T[:, :3, :3])
    with np.errstate(divide="ignore", invalid="ignore"):
        speed_mps = np.where(dt_s > 0, distance_m / dt_s, np.where(distance_m > 0, np.inf, 0.0))
        rate_rad_s = np.where(dt_s > 0, angle_rad / dt_s, np.where(angle_rad > 0, np.inf, 0.0))
    return speed_mps, rate_rad_s


def plausible_increments(where: str | Path, T_prev_curr: np.ndarray, dt_s: np.ndarray, checks: InputChecks) -> np.ndarray:
    """Mask of the increments the vehicle can make (no faster than ``checks.max_speed_mps`` and
    ``checks.max_rotation_rate_rad_s``). The others are to be skipped: one warning says how many
    and the first, with its figures."""
    speed_mps, rate_rad_s = increment_rates(T_prev_curr, dt_s)
    too_fast, turns_too_fast = speed_mps > checks.max_speed_mps, rate_rad_s > checks.max_rotation_rate_rad_s
    ok = ~(too_fast | turns_too_fast)
    if not ok.all():
        i = int(np.argmin(ok))
        why = (
            f"{speed_mps[i]:.3g} m/s > input_checks.max_speed_mps = {checks.max_speed_mps:g} m/s"
            if too_fast[i]
            else f"{rate_rad_s[i]:.3g} rad/s > input_checks.max_rotation_rate_rad_s = {checks.max_rotation_rate_rad_s:g} rad/s"
        )
        log.warning(
            "%s: %d of %d odometry increments are beyond the vehicle's motion (first: index %d, %s): skipped, their time bridged at the last increment's rate",
            where,
            int((~ok).sum()),
            len(ok),
            i,
            why,
        )
    return ok


# ----------------------------------------------------------------------------------------------
# images and scans


def check_image_size(path: str | Path, image: np.ndarray, camera: CameraSpec) -> None:
    """Refuse an image of another size than the rig's camera: a :class:`DatasetError` naming the image."""
    height_px, width_px = image.shape[:2]
    if (width_px, height_px) != (camera.width_px, camera.height_px):
        raise DatasetError(
            path,
            f"image is {width_px}x{height_px} px but the rig's camera is {camera.width_px}x{camera.height_px} px "
            "(camera.width_px x camera.height_px): the rig is not this camera's",
        )


def image_std_dn(image: np.ndarray) -> float:
    """Standard deviation of the image's grey levels (a BGR image made grey first), DN."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    return float(cv2.meanStdDev(grey)[1][0, 0])


class TextureWatch:
    """Marks the camera frames without texture (:attr:`InputChecks.min_image_std_dn`) and those
    bit-identical to the frame before (frozen), and warns once for each stretch of either, when it begins."""

    def __init__(self, where: str | Path, checks: InputChecks):
        self.where = where
        self.min_image_std_dn = checks.min_image_std_dn
        self._stretch_start: int | None = None  # index of the first frame of the textureless stretch going on
        self._frozen_start: int | None = None  # ... of the frozen one
        self._previous: CameraFrame | None = None

    def frame(self, frame: CameraFrame, std_dn: float | None = None, where: str | Path | None = None) -> CameraFrame:
        """``frame``, marked ``textureless`` when its grey levels' deviation (``std_dn``, computed when
        None) is below the limit or when its image is the previous frame's, bit for bit; a warning
        names ``where`` (the image's file; None: the stream's)."""
        previous, self._previous = self._previous, frame
        std_dn = image_std_dn(frame.image) if std_dn is None else std_dn
        if std_dn < self.min_image_std_dn:
            self._end_frozen(frame)
            return self._textureless(frame, std_dn, where)
        if self._stretch_start is not None:
            log.info("%s: frames %d to %d had no texture", self.where, self._stretch_start, frame.index - 1)
            self._stretch_start = None
        if previous is not None and np.array_equal(frame.image, previous.image):
            return self._frozen(frame, previous, where)
        self._end_frozen(frame)
        return frame

    def _textureless(self, frame: CameraFrame, std_dn: float, where: str | Path | None) -> CameraFrame:
        if self._stretch_start is None:
            self._stretch_start = frame.index
            log.warning(
                "%s: frame %d at %.3f s has no texture (grey-level std %.2f DN < input_checks.min_image_std_dn = %g DN): "
                "not tracked, its pose predicted, until a frame with texture comes",
                self.where if where is None else where,
                frame.index,
                frame.t_s,
                std_dn,
                self.min_image_std_dn,
            )
        return dataclasses.replace(frame, textureless=True)

    def _frozen(self, frame: CameraFrame, previous: CameraFrame, where: str | Path | None) -> CameraFrame:
        if self._frozen_start is None:
            self._frozen_start = frame.index
            log.warning(
                "%s: frame %d at %.3f s is bit-identical to frame %d (a frozen camera driver repeating its image?): "
                "not tracked, its pose predicted, until a frame that differs comes",
                self.where if where is None else where,
                frame.index,
                frame.t_s,
                previous.index,
            )
        return dataclasses.replace(frame, textureless=True)

    def _end_frozen(self, frame: CameraFrame) -> None:
        if self._frozen_start is not None:
            log.info("%s: frames %d to %d repeated the frame before them", self.where, self._frozen_start, frame.index - 1)
        self._frozen_start = None


def warn_if_no_laser(where: str | Path, ranges_m: np.ndarray, laser: LaserSpec) -> None:
    """Say when a log has no laser scan at all, or when none of its scans (n,B) holds a valid return
    (:meth:`~dem_graph.geometry.rig.LaserSpec.valid_ranges`): the map then holds camera points only.
    When most finite ranges lie beyond ``laser.range_max_m`` the warning asks after their unit."""
    if len(ranges_m) == 0:
        log.warning("%s: no laser scans: the map will hold only camera points", where)
        return
    if np.any(laser.valid_ranges(ranges_m)):
        return
    finite = np.asarray(ranges_m)[np.isfinite(ranges_m)]
    beyond = int(np.count_nonzero(finite > laser.range_max_m))
    if finite.size == 0:
        why = "every range is NaN (no return)"
    elif beyond > finite.size / 2:
        why = (
            f"{beyond} of {finite.size} finite ranges lie beyond laser.range_max_m = {laser.range_max_m:g} m "
            f"(median {float(np.median(finite)):.4g}): are they in millimetres, not metres?"
        )
    else:
        why = f"every finite range lies outside laser.range_min_m to range_max_m ({laser.range_min_m:g} to {laser.range_max_m:g} m)"
    log.warning("%s: none of the %d scans has a valid return: %s; no laser return is used, the map will hold only camera points", where, len(ranges_m), why)


__all__ = [
    "NONFINITE",
    "STAMP_NOT_AFTER",
    "WRONG_SHAPE",
    "InputChecks",
    "SkippedMessages",
    "TextureWatch",
    "check_covariances",
    "check_image_size",
    "check_time_jumps",
    "covariance_problems",
    "first_time_jump",
    "image_std_dn",
    "increasing_stamps",
    "increment_rates",
    "plausible_increments",
    "repair_unknown_covariances",
    "time_text",
    "unknown_covariances",
    "warn_if_no_laser",
]
