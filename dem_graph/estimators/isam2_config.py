"""The graph estimator's options (:mod:`dem_graph.estimators.isam2`), and the settings it shares
with the EKF baselines."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field

from dem_graph.config_types import StrictModel
from dem_graph.estimators.settings import SharedSettings

BATCH_KEYFRAME_EVERY = 5
"""isam2-batch's online pass: a keyframe every this many frames, unless ``batch_keyframe_every`` says otherwise or the laser is tied."""


class Isam2Options(StrictModel):
    """What only the graph estimator has."""

    keyframe_every: int | None = Field(
        None,
        ge=1,
        description="a keyframe every this many frames (1: every frame a pose of the graph; more is faster and less accurate, docs/isam2_design.md). "
        "Unset: 1, except for the graph in a second process whose results come when ready (the vehicle): there as many frames as it takes "
        "for the live points, all landmarks, to stay within graph_landmarks_per_frame (ceil(live points / graph_landmarks_per_frame))",
    )
    graph_landmarks_per_frame: int = Field(
        250,
        ge=1,
        description="the vehicle's graph (graph_process, results when ready) with keyframe_every unset: the landmark observations it takes per "
        "camera frame at most, which sets its keyframe spacing. 250: 235-243 landmarks a frame kept up with the camera on two cores of an AMD "
        "EPYC (a keyframe every frame at 235 live points, every second frame at 486; docs/isam2_design.md)",
    )
    observation_every: int | None = Field(
        None,
        ge=1,
        description="each landmark's observation goes to the graph at every this many keyframes, the landmarks taking turns, and carries the frames "
        "since its last (sigma_px / sqrt(frames)). An update's cost grows with the square of the keyframes that saw each landmark: 2 makes iSAM2's "
        "solve about three times cheaper and a keyframe's graph work about 40 % less, at no accuracy that shows (eight paper seeds in this "
        "process, two draws each: mean ATE 0.068 against 0.062 m, docs/isam2_design.md). "
        "Unset: 2 with graph_process and no graph_delay_keyframes (so that the graph keeps up at the camera's rate on two cores), else 1",
    )
    keyframe_min_live_fraction: float = Field(0.8, ge=0, le=1, description="also a keyframe when the live points fall below this fraction of the cap (new points enter at keyframes)")
    lag_s: float = Field(1.5, gt=0, description="fixed lag of the smoother, seconds: older variables are marginalised")
    marginalize_every_s: float = Field(
        0.5, gt=0, description="the window is cut back to the lag once it spans lag_s + this, seconds (one batch elimination of the window, made after a result has gone)"
    )
    relinearize_threshold: float = Field(0.01, gt=0, description="iSAM2 relinearises a variable whose update exceeds this")
    relinearize_skip: int = Field(1, ge=1, description="iSAM2 checks for relinearisation every this many updates")
    optimizer: Literal["dogleg", "gauss_newton"] = Field(
        "gauss_newton",
        description="iSAM2's step: plain Gauss-Newton, or dogleg (a trust region, which evaluates the whole window's error at every update: a third "
        "of an update's time). Dogleg was chosen when Gauss-Newton steps oscillated along the window's weakly observed height and tilt; with the "
        "landmarks ordered before the poses, 24 whole `paper` runs with Gauss-Newton did not (docs/isam2_design.md)",
    )
    keyframe_weighting: bool = Field(
        True, description="a keyframe observation carries the information of the frames that tracked the point since its last keyframe observation (sigma_px / sqrt(n))"
    )
    track_correlation: float = Field(
        0.0, ge=0, lt=1, description="lag-1 autocorrelation of a track's pixel errors from frame to frame (AR(1)); n frames then carry the information of n_eff < n independent ones"
    )
    split_link_sigma_m: float = Field(
        0.005, gt=0, description="a patch refresh starts a new landmark, tied to the old one with this sigma (the ground point under the new patch is a few mm away), metres"
    )
    robust: bool = Field(True, description="Huber kernel on projection factors and per-frame pixels")
    laser_ties: Literal["auto", "on", "off"] = Field(
        "auto",
        description="tie landmarks to the scans of their ground while both are in the window, for a laser whose line the camera does not see "
        "(on a bumper, below the image): its ranges then give the scale and the tilt (dem_graph.estimators.laser_ties, docs/pushbroom.md). "
        "auto: on when the rig's laser line is out of the camera's view (geometry.ground_view), off when the paper's laser points see it",
    )
    outlier_chi2: float = Field(9.21, gt=0, description="an observation whose normalised residual after the frame's pose update exceeds this (chi-square, 2 dof; 9.21 = 99 %) stays out of the graph")
    pose_covariance_every_s: float = Field(
        1.0, ge=0, description="take a keyframe pose's marginal covariance from the smoother (a costly call) at most this often, seconds; in between it is carried by odometry; 0: never (the covariance relative to the map)"
    )
    graph_process: bool = Field(
        False,
        description="run the graph (iSAM2 updates, the window's cut, marginals) in a second process, on another core: a frame then costs the front end's time, "
        "and the graph's results reach the front end one or more keyframes later (a run then depends on the timing); false: each keyframe's update ends in its own frame",
    )
    graph_max_landmarks: int | None = Field(
        None,
        ge=1,
        description="live points that are landmarks of the graph, at most: a new point beyond it stays in the front end only (its own estimate, "
        "updated at each keyframe with the pose held fixed and moved with the graph's corrections). New laser points are taken before camera "
        "points. Unset: no bound (the vehicle's graph spaces its keyframes instead, graph_landmarks_per_frame)",
    )
    graph_max_lag: int | None = Field(
        None,
        ge=1,
        description="graph_process: keyframes the front end may run ahead of the graph's newest result; beyond, see graph_when_behind. "
        "Unset: 3 keyframes per frame of keyframe spacing (3 at a keyframe every frame, 6 at every second frame: the window's cut, whose "
        "cost follows the landmarks, then passes without merging keyframes)",
    )
    graph_process_nice: int = Field(
        10,
        ge=0,
        le=19,
        description="graph_process: the second process's priority lowered by this much (Unix nice): where the cores are short (another program "
        "busy on the vehicle), the front end's frames go first and the graph falls behind and merges keyframes, instead of the frames waiting "
        "for their share of a core (docs/isam2_design.md); 0: the same priority as the front end",
    )
    graph_when_behind: Literal["merge", "wait"] | None = Field(
        None,
        description="graph_process: what a frame due to be a keyframe does when the graph is graph_max_lag keyframes behind. merge: it is not made a "
        "keyframe, its observations go with the next one (counted as keyframes_merged), so that no frame waits for the graph, as on a vehicle; "
        "wait: it waits for the graph (a log replayed faster than recorded then goes at the graph's pace). Unset: wait in a run that replays its "
        "log as fast as possible (realtime: false), merge otherwise",
    )
    graph_delay_keyframes: int = Field(
        0,
        ge=0,
        description="hand each graph result back exactly this many keyframes late, reproducibly. In this process: as a second process's come "
        "back (studies and tests of that lag). With graph_process: the second process takes one keyframe at a time and the front end waits "
        "for a result that is not back when due, so its updates run beside the next keyframes' frames and the run is the same, number for "
        "number, as in this process with that delay (for offline runs: a frame may wait; graph_process_nice is not applied, the frames "
        "waiting for it). 0: in this process, in the frame that sent it; "
        "with graph_process, whenever it comes (a run then depends on the timing)",
    )
    batch_keyframe_every: int | None = Field(
        None,
        ge=1,
        description="isam2-batch: keyframe_every of its online pass, which only associates the data (the batch has a pose for every frame); "
        "fewer keyframes make that pass cheaper (docs/isam2_design.md). Unset: 5, and 1 with laser_ties on (on the car scenario's mis-mounted "
        "rig the DEM's error was 15-62 cm with keyframes 2-5 frames apart, 2.4 cm with every frame: docs/pushbroom.md)",
    )
    batch_graph_delay_keyframes: int = Field(
        0,
        ge=0,
        description="isam2-batch: run its online pass's graph in a second process, each result handed back exactly this many keyframes late "
        "(graph_delay_keyframes with graph_process: reproducible), so that the graph's updates run beside the next keyframes' tracking. "
        "1 made the online pass of paper seed 0 a fifth faster (23.9 against 29.8 s), and its association, which decides the batch's answer, "
        "another draw (eight seeds: mean ATE 0.083 against 0.071 m, docs/isam2_design.md). 0: as graph_process and graph_delay_keyframes say (by default in this "
        "process, each result in the frame that sent it). Ignored with graph_process (the second process's results then come when ready)",
    )
    batch_max_iterations: int = Field(10, ge=1, description="isam2-batch: Levenberg-Marquardt iterations at most")
    batch_relative_error_tol: float = Field(1e-3, gt=0, description="isam2-batch: stop when the error falls by less than this fraction")
    batch_marginals: bool = Field(
        True,
        description="isam2-batch: give each frame the marginal covariance of its pose in the batch's final graph (gtsam.Marginals at the solution), "
        "so that the run's pose NEES is the batch's own; false: the frames keep the online pass's covariances (and the marginals' cost is saved)",
    )

class Isam2Config(SharedSettings, Isam2Options):
    """The graph estimator's options with the settings every estimator shares."""

    batch: bool = Field(False, description="record every observation and smooth the whole log at the end (isam2-batch)")

    @property
    def observation_spacing(self) -> int:
        """Keyframes between a landmark's observations in the graph: ``observation_every``, unset: 2 with the graph in
        a second process whose results come when ready, and 1 in this one or handed back at a fixed delay; 1 for the
        batch's online pass (its keyframes are 5 frames apart already, and the batch has every frame's observations)."""
        if self.batch:
            return 1
        if self.observation_every is not None:
            return self.observation_every
        return 2 if self.graph_process and not self.graph_delay_keyframes else 1

    @property
    def graph_landmark_budget(self) -> int | None:
        """Live points that may be landmarks of the graph (None: all): ``graph_max_landmarks``; no bound
        for the batch."""
        return None if self.batch else self.graph_max_landmarks

    @property
    def results_when_ready(self) -> bool:
        """The graph runs in a second process whose results come when ready, at no fixed delay (the vehicle; :attr:`graph_placement`)."""
        in_second_process, delay = self.graph_placement
        return in_second_process and not delay

    @property
    def graph_placement(self) -> tuple[bool, int]:
        """Where the graph runs and how late its results are handed back: (in a second process, the delay in
        keyframes). The batch's online pass: in a second process, ``batch_graph_delay_keyframes`` late, when that
        is above 0 and ``graph_process`` is not set; otherwise ``graph_process`` and ``graph_delay_keyframes``. A
        second process with a delay of 0 hands its results back when they come; with more, exactly that late."""
        if self.batch and not self.graph_process and self.batch_graph_delay_keyframes > 0:
            return True, self.batch_graph_delay_keyframes
        return self.graph_process, self.graph_delay_keyframes

    def keyframe_spacing_for(self, live_points: int) -> int:
        """Frames between keyframes with ``live_points`` live points: ``batch_keyframe_every`` for the
        batch's online pass; ``keyframe_every`` when set; unset, on the vehicle's graph, enough frames
        for its landmarks to stay within ``graph_landmarks_per_frame`` (every live point is one there
        unless ``graph_max_landmarks`` bounds them), and 1 elsewhere."""
        if self.batch:
            return self.batch_keyframe_every or BATCH_KEYFRAME_EVERY
        if self.keyframe_every is not None:
            return self.keyframe_every
        if not self.results_when_ready:
            return 1
        landmarks = live_points if self.graph_max_landmarks is None else min(live_points, self.graph_max_landmarks)
        return max(1, math.ceil(landmarks / self.graph_landmarks_per_frame))

    @property
    def keyframe_spacing(self) -> int:
        """The most frames between keyframes in this run (at ``frontend.max_points`` live points; see :meth:`keyframe_spacing_for`)."""
        return self.keyframe_spacing_for(self.frontend.max_points)

    def graph_lag_limit(self, spacing: int) -> int:
        """Keyframes the front end may run ahead of the graph's newest result at a keyframe every
        ``spacing`` frames: ``graph_max_lag``, unset 3 per frame of spacing."""
        return self.graph_max_lag if self.graph_max_lag is not None else 3 * spacing


__all__ = ["BATCH_KEYFRAME_EVERY", "Isam2Config", "Isam2Options"]
