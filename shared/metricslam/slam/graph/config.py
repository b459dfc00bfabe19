"""Frozen algorithm configuration of the global pose graph, loop closure and scale factors.

Sigmas are standard deviations in the Sim(3) tangent ``[ω (rad), u (keyframe units), λ = log s]``.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class LoopConfig(BaseModel):
    """Place recognition + geometric verification parameters (see :mod:`metricslam.slam.loop`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = True
    #: a new tracking segment relocalizes in the session's own map (:mod:`metricslam.slam.map.segments`)
    relocalize_segments: bool = True
    n_orb_features: int = Field(default=500, gt=0)
    image_scale: float = Field(default=0.5, gt=0, le=1)  # ORB runs on the image resized by this
    keyframe_stride: int = Field(default=2, ge=1)  # only every n-th keyframe is indexed/queried
    fast_corners: int = Field(default=0, ge=0)  # experimental: FAST corners borrowing nearby landmark depth
    vocabulary_words: int = Field(default=400, gt=8)
    vocabulary_train_keyframes: int = Field(default=12, gt=0)
    skip_recent_keyframes: int = Field(default=30, ge=1)
    min_score_ratio: float = Field(default=0.3, gt=0)
    n_candidates: int = Field(default=5, gt=0)
    min_matches: int = Field(default=12, gt=3)
    min_inliers: int = Field(default=12, gt=3)
    min_inlier_ratio: float = Field(default=0.4, gt=0, le=1)
    ransac_iterations: int = Field(default=200, gt=0)
    reprojection_threshold_px: float = Field(default=3.0, gt=0)
    hamming_ratio: float = Field(default=0.8, gt=0, le=1)
    # indexed keyframes between accepted loops: a revisit is closed once, not every few keyframes
    # along it; each loop costs a batch re-solve and ~0.25 MB of ISAM2 (20, was 5: session 11's
    # pre-registered rule, docs/history/rule_loop_memory_session11.md)
    min_keyframes_between_loops: int = Field(default=20, ge=0)
    # all-corner verification (:mod:`metricslam.slam.loop.corners`); "landmarks" = VO landmarks only
    verification: str = Field(default="corners", pattern="^(corners|landmarks)$")
    n_corner_features: int = Field(default=1000, gt=0)  # full-resolution ORB corners per keyframe
    essential_threshold_px: float = Field(default=1.0, gt=0)  # essential-matrix RANSAC threshold
    corner_reprojection_threshold_px: float = Field(default=6.0, gt=0)  # Sim(3) RANSAC, two-way
    min_depth_inliers: int = Field(default=15, gt=3)  # Sim(3) inliers among corners with depth
    min_depth_inlier_ratio: float = Field(default=0.3, gt=0, le=1)
    # what measures a verified loop's translation and scale: "geometric" (corners triangulated
    # against the previous keyframe, :mod:`metricslam.slam.loop.geometric_sim3`; network depth
    # only verifies) or "network" (the verification's own points: network depth in scale mode)
    measurement: str = Field(default="geometric", pattern="^(geometric|network)$")
    rotation_sigma_rad: float = Field(default=0.01, gt=0)  # verified rotation (PnP 0.03-0.7 deg off)
    geometric_reprojection_px: float = Field(default=3.0, gt=0)
    min_geometric_points: int = Field(default=6, ge=3)  # old-side triangulated corners (translation)
    min_geometric_scale_points: int = Field(default=5, ge=2)  # both-sided (scale)
    # indexed keyframes the place-recognition database holds (a bag-of-words row each in RAM;
    # ~1000 corners each, packed: :class:`metricslam.slam.loop.corners.PackedCorners`, on disk
    # with ``features_on_disk``); older ones are forgotten, so a long drive's memory and disk
    # stay bounded.
    # 1000 = every keyframe of the longest benchmark run (1271 keyframes, stride 2) kept.
    max_database_keyframes: int = Field(default=1000, ge=1)
    # the database's verification features (packed corners, landmark features) in a temporary
    # SQLite file, read back only for a query's candidates, so they are not resident
    # (:mod:`metricslam.slam.loop.feature_store`); false keeps them in RAM (e.g. no writable
    # temporary directory). Chosen by docs/history/rule_loop_spill_session12c.md.
    features_on_disk: bool = True


#: depth requests an OFFLINE run lets wait (``metricslam run --depth-queue``): it waits for every
#: keyframe's depth instead of dropping requests, so its result does not depend on machine load.
#: The live default (``GraphConfig.depth_queue_size``) stays short: a late map is worth less
#: there than the next frame.
OFFLINE_DEPTH_QUEUE_SIZE = 256


class GraphConfig(BaseModel):
    """Global Sim(3) graph parameters (paper eq. 13).

    Attributes:
        odom_sigma_rot_rad: odometry rotation sigma per keyframe step (0.001 rad: twice the
            synthetic VO's measured rotation noise per keyframe, r_rel 0.21 °/100 m without
            loops; the former 0.005 let a loop correction bend every segment by ~1-2.6 ° per
            100 frames instead of changing scale, t_rel 4.3 -> 5.1 % on the 2 km drive).
        odom_sigma_trans_rel: odometry translation sigma as a fraction of the step length.
        odom_sigma_trans_min: floor of the translation sigma (keyframe units).
        odom_sigma_log_scale: odometry log-scale sigma per keyframe step: the monocular VO's
            scale drift as a random walk. 0.006 = measured on a validation drive (synthetic,
            KITTI 05's path, seed 505: variance of the log local scale grows 3.8e-5 per
            keyframe; 0.0066 on the 2 km drive along KITTI 00), ``bench/results/scale_noise.md``.
            The former 0.03 let the trajectory's scale follow the network keyframe by keyframe.
        scale_sigma_log: sigma of one landmark's log-scale measurement ``log(ξ_j / z_j)``.
        scale_sigma_floor_log: floor of a keyframe's summarized scale-factor sigma
            (``per_keyframe`` mode). The network's error is mostly per image, so ``σ/√n`` over one
            image's landmarks would overstate the information, and it is correlated from image to
            image along the road: on the validation drive the per-image log error has sd 0.053-0.059
            and an integrated correlation length of 11-14 keyframes (26-33 frames), so N
            keyframes carry about N/14 independent measurements. Each keyframe's factor gets
            0.059·√14 ≈ 0.2 (``bench/results/scale_noise.md``); with 0.006 per-step drift the
            trajectory's scale averages the network over ~1,000 keyframes instead of ~4.
        scale_huber_k: Huber threshold ε_s on the whitened scale residual.
        scale_factor_mode: "per_keyframe" (one factor at the keyframe's Huber M-estimate, default)
            or "per_landmark" (eq. 13 literally); see :mod:`.scale_factor`.
        max_scale_landmarks: at most this many landmarks per keyframe give scale factors
            (the strongest-parallax ones are not known here, so an even subsample).
        min_inv_depth_per_m / max_inv_depth_per_m: network inverse depths outside are unusable.
        scale_max_depth_m: range gate of the scale factors (None = off): only landmarks whose
            metric depth, by the keyframe's own scale estimate (iterated, see
            :func:`.scale_factor.scale_measurements`), is at most this far give measurements —
            beyond it a single coarse image hardly constrains depth and the network regresses
            to its mean (``bench/scale_measurements.py``: x0.4-0.6 beyond 40 m on both
            validation drives). At least ``scale_gate_min_landmarks`` (the nearest) are kept.
        loop_sigma_rot_rad / loop_sigma_trans_rel / loop_sigma_log_scale: loop factor sigmas.
        loop_kernel: robust kernel on loop factors ("huber", convex, default: a gated loop must be
            able to pull a drifted map home; "cauchy"; "dcs" refuses large corrections).
        loop_kernel_param: its parameter (whitened units).
        loop_reject_chi2: after a solve, a loop whose whitened squared error exceeds this is
            removed as a false loop.
        factorization: ISAM2 / batch LM elimination. "QR" (default): gtsam's Cholesky treats
            pivots below an absolute 1e-6 as zero and so reports a long loop-free chain, whose
            far end is known only to hundreds of metres, as indeterminate.
        relinearize_threshold / relinearize_skip: ISAM2 relinearization controls.
        extra_iterations: extra ISAM2 updates after a loop or a batch of scale factors.
        depth_queue_size: bounded depth-request queue; when full the OLDEST request is dropped.
        min_scale_factors_established: scale factors needed before ``scale_established``.
        inline: run depth and solve inside ``on_keyframe_marginalized`` (deterministic, for
            tests and offline benchmarks); False runs them in worker threads.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    odom_sigma_rot_rad: float = Field(default=0.001, gt=0)
    odom_sigma_trans_rel: float = Field(default=0.05, gt=0)
    odom_sigma_trans_min: float = Field(default=0.01, gt=0)
    odom_sigma_log_scale: float = Field(default=0.006, gt=0)
    use_vo_information: bool = False
    scale_sigma_log: float = Field(default=0.15, gt=0)
    scale_sigma_floor_log: float = Field(default=0.2, ge=0)
    scale_huber_k: float = Field(default=1.345, gt=0)
    scale_factor_mode: str = Field(default="per_keyframe", pattern="^(per_keyframe|per_landmark)$")
    max_scale_landmarks: int = Field(default=48, gt=0)
    min_inv_depth_per_m: float = Field(default=1.0 / 80.0, gt=0)
    max_inv_depth_per_m: float = Field(default=1.0 / 1.5, gt=0)
    scale_max_depth_m: float | None = Field(default=None, gt=0)
    scale_gate_min_landmarks: int = Field(default=8, ge=1)
    loop_sigma_rot_rad: float = Field(default=0.01, gt=0)
    loop_sigma_trans_rel: float = Field(default=0.05, gt=0)
    loop_sigma_log_scale: float = Field(default=0.05, gt=0)
    loop_kernel: str = Field(default="huber", pattern="^(dcs|cauchy|huber)$")
    loop_kernel_param: float = Field(default=2.0, gt=0)
    loop_reject_chi2: float = Field(default=50.0, gt=0)
    factorization: str = Field(default="QR", pattern="^(QR|CHOLESKY)$")
    relinearize_threshold: float = Field(default=0.01, gt=0)
    relinearize_skip: int = Field(default=10, ge=1)
    extra_iterations: int = Field(default=0, ge=0)
    depth_queue_size: int = Field(default=4, ge=1)
    min_scale_factors_established: int = Field(default=10, ge=1)
    inline: bool = False
    loop: LoopConfig = LoopConfig()
