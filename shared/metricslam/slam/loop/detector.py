"""``LoopDetector``: per keyframe, ORB bag-of-words retrieval then geometric verification.

Candidates are keyframes older than the ``skip_recent_keyframes`` most recent indexed ones (every
``keyframe_stride``-th keyframe is indexed) whose cosine
score reaches ``min_score_ratio`` times the score of the query against its immediate predecessor
(DBoW2's normalization: what "similar" means depends on the scene), best first, at most
``n_candidates``; each is verified with all ORB corners of both keyframes
(:func:`metricslam.slam.loop.corners.verify_corners`; corner depth from the network's metric
inverse-depth map in scale mode, from triangulation against the previous keyframe without it),
falling back to the VO-landmark verification (:func:`metricslam.slam.loop.verification.verify`)
when a keyframe has no corner depth. The database keeps the newest ``max_database_keyframes``
indexed keyframes; older ones are forgotten (bounded memory on a long drive). Their corners are
held packed (:class:`~metricslam.slam.loop.corners.PackedCorners`: lossless, half the memory) and,
with ``features_on_disk``, with the landmark features in a temporary SQLite file
(:class:`~metricslam.slam.loop.feature_store.FeatureStore`): only the bag-of-words rows stay in RAM.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.depth.model import to_gray_u8
from metricslam.depth.sample import sample_map
from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.loop import corners as corner_mod
from metricslam.slam.loop.feature_store import FeatureStore
from metricslam.slam.loop.verification import (
    landmark_features,
    verify,
)
from metricslam.slam.loop.vocabulary import BinaryVocabulary, BowDatabase


def retrieval_orb(config: LoopConfig) -> cv2.ORB:
    """The ORB detector whose descriptors feed the bag-of-words retrieval."""
    return cv2.ORB_create(nfeatures=config.n_orb_features, nlevels=4, fastThreshold=12)


def retrieval_descriptors(orb: cv2.ORB, gray: np.ndarray, image_scale: float) -> np.ndarray:
    """Retrieval descriptors (N, 32) uint8 of a gray (H, W) uint8 image. ORB detection costs per
    pixel, so it runs on the image resized by ``image_scale``; landmark descriptors
    (verification) stay at full resolution with a single-level ORB (cheap)."""
    small = gray if image_scale == 1.0 else cv2.resize(
        gray, (round(gray.shape[1] * image_scale), round(gray.shape[0] * image_scale)),
        interpolation=cv2.INTER_AREA)
    _, desc = orb.detectAndCompute(small, None)
    return desc if desc is not None else np.zeros((0, 32), np.uint8)


@dataclass(frozen=True)
class LoopCandidate:
    """A verified loop: ``S_old_new`` (4, 4) maps the new keyframe's frame/units into the old's;
    ``sigmas`` (7,) ``[ω, u, λ]`` when the measurement came with its own covariance."""

    kf_old: int
    kf_new: int
    S_old_new: np.ndarray
    n_inliers: int
    score: float
    sigmas: np.ndarray | None = None


class LoopDetector:
    """Place recognition over keyframes (see module docstring). Not thread-safe."""

    def __init__(self, config: LoopConfig | None = None, seed: int = 0) -> None:
        self.config = config or LoopConfig()
        self._calls = 0
        self._orb = retrieval_orb(self.config)
        self._orb_landmarks = cv2.ORB_create(nlevels=1)
        self._fast = cv2.FastFeatureDetector_create(threshold=20, nonmaxSuppression=True)
        self._vocab: BinaryVocabulary | None = None
        self._db: BowDatabase | None = None
        self._pending: list[tuple[int, np.ndarray]] = []  # (kf_id, ORB descriptors) before training
        self._store = FeatureStore(on_disk=self.config.features_on_disk)  # verification features
        self._orb_corners = cv2.ORB_create(nfeatures=self.config.n_corner_features, nlevels=4,
                                           fastThreshold=12)
        self._prev_corners: tuple[np.ndarray, np.ndarray] | None = None  # last keyframe's (uv, desc)
        self.n_corner_verified = 0
        self._order: list[int] = []
        self._last_loop_at = -10**9
        self._rng = np.random.default_rng(seed)
        self.n_queries = 0
        self.n_verified = 0

    def add_and_query(self, kf_id: int, image: np.ndarray, camera: PinholeCamera,
                      landmarks_uv_px: np.ndarray, landmarks_inv_depth: np.ndarray,
                      inv_depth_map: np.ndarray | None = None,
                      T_prevkf_kf: np.ndarray | None = None) -> list[LoopCandidate]:
        """Add keyframe ``kf_id`` and return verified loops to older keyframes (maybe empty).

        Only every ``keyframe_stride``-th call does any work (consecutive keyframes see nearly
        the same place; a revisit spans many keyframes).

        Args:
            image / camera: the keyframe image (H, W) and its intrinsics.
            landmarks_uv_px / landmarks_inv_depth: VO landmarks (M, 2) px and ξ (M,) in the
                keyframe's own units.
            inv_depth_map: the network's metric inverse depth (h, w) 1/m covering the image
                (scale mode), or None (``--no-scale``: corners are triangulated instead).
            T_prevkf_kf: (4, 4) VO pose relative to the previous keyframe (k's units), used to
                triangulate corners when there is no depth map.
        """
        self._calls += 1
        gray = to_gray_u8(image)
        corner_mode = self.config.verification == "corners"
        uv_c = desc_c = None
        if corner_mode:  # every keyframe: a queried keyframe triangulates against its predecessor
            uv_c, desc_c = corner_mod.detect_corners(self._orb_corners, gray)
        prev, self._prev_corners = self._prev_corners, ((uv_c, desc_c) if uv_c is not None else None)
        if (self._calls - 1) % self.config.keyframe_stride:
            return []
        new_corners = packed = None
        if corner_mode:
            new_corners = self._corner_features(uv_c, desc_c, camera, gray.shape, landmarks_uv_px,
                                                landmarks_inv_depth, inv_depth_map, T_prevkf_kf, prev)
            packed = corner_mod.PackedCorners.pack(new_corners, camera)
        desc = retrieval_descriptors(self._orb, gray, self.config.image_scale)
        extra = None
        if self.config.fast_corners > 0:
            kps = self._fast.detect(gray, None)
            kps = sorted(kps, key=lambda k: -k.response)[: self.config.fast_corners]
            extra = np.array([k.pt for k in kps], dtype=float).reshape(-1, 2)
        new_features = landmark_features(self._orb_landmarks, gray, camera, landmarks_uv_px,
                                         landmarks_inv_depth, extra_uv_px=extra)
        self._store.put(kf_id, new_features, packed)
        self._order.append(kf_id)
        self._forget_beyond_cap()
        if self._vocab is None:
            self._pending.append((kf_id, desc))
            if len(self._pending) >= self.config.vocabulary_train_keyframes:
                self._vocab = BinaryVocabulary.train([d for _, d in self._pending],
                                                     self.config.vocabulary_words)
                self._db = BowDatabase(self._vocab.size)
                for k, d in self._pending:
                    self._db.add(k, self._vocab.bow(d))
                self._pending = []
            return []
        v = self._vocab.bow(desc)
        self._db.add(kf_id, v)
        n = len(self._db)
        self.n_queries += 1
        cfg = self.config
        if n - 1 <= cfg.skip_recent_keyframes or n - 1 - self._last_loop_at < cfg.min_keyframes_between_loops:
            return []
        ref = float(self._db.row(n - 2) @ v)
        if ref <= 0:
            return []
        ids, scores = self._db.scores(v, upto=n - 1 - cfg.skip_recent_keyframes)
        order = np.argsort(-scores)[: cfg.n_candidates]
        out: list[LoopCandidate] = []
        for i in order:
            if scores[i] < cfg.min_score_ratio * ref:
                break
            old = int(ids[i])
            res = None
            n_old = self._store.n_with_depth(old)
            co = None
            if new_corners is not None and n_old is not None and min(new_corners.n_with_depth, n_old) >= cfg.min_depth_inliers:
                co = self._store.corners(old)
            if co is not None:
                res = corner_mod.verify_corners(new_corners, co.unpack(), camera, cfg, self._rng)
                self.n_corner_verified += res is not None
            else:
                old_features = self._store.landmarks(old)
                if old_features is None:  # unreadable (counted by the store): next candidate
                    continue
                res = verify(new_features, old_features, camera, cfg, self._rng)
            if res is not None:
                out.append(LoopCandidate(old, kf_id, res.S_old_new, res.n_inliers, float(scores[i]), res.sigmas))
                self._last_loop_at = n - 1
                self.n_verified += 1
                break
        return out

    @property
    def store_counters(self) -> dict[str, int]:
        """The feature store's degradations: entries kept in RAM because a write failed, and
        candidate reads that failed (both 0 when the temporary directory works)."""
        return {"loop_features_in_ram": self._store.n_kept_in_memory,
                "loop_feature_read_errors": self._store.n_read_errors}

    def export_database(self) -> tuple[BinaryVocabulary, np.ndarray, np.ndarray, list[tuple]] | None:
        """What a saved map keeps of the place-recognition database (:mod:`metricslam.slam.map`):
        ``(vocabulary, kf_ids (M,), bag-of-words rows (M, k), features per row)``, each row's
        features ``(uv_px (n, 2), descriptors (n, 32), points (n, 3) keyframe VO units, exact
        (n,))``: its ORB corners with depth, then its VO-landmark features (``exact``). None
        when no keyframe was indexed. A run too short to have trained its vocabulary trains
        one here from the keyframes it indexed (the detector itself is not changed)."""
        vocab, db = self._vocab, self._db
        if vocab is None:
            sets = [d for _, d in self._pending if d is not None and len(d)]
            if not sets:
                return None
            vocab = BinaryVocabulary.train(sets, self.config.vocabulary_words)
            db = BowDatabase(vocab.size)
            for k, d in self._pending:
                db.add(k, vocab.bow(d))
        ids, rows = db.rows()
        keep, feats = [], []
        for i, k in enumerate(ids):
            lm = self._store.landmarks(int(k))
            if lm is None:
                continue
            parts = [(lm.uv_px, lm.descriptors, lm.points,
                      np.ones(len(lm.points), bool) if lm.exact is None else lm.exact)]
            packed = self._store.corners(int(k))
            if packed is not None:
                c = packed.unpack()
                ok = np.isfinite(c.points).all(axis=1)
                parts.insert(0, (c.uv_px[ok], c.descriptors[ok], c.points[ok], np.zeros(int(ok.sum()), bool)))
            keep.append(i)
            feats.append((np.concatenate([np.asarray(p[0], float).reshape(-1, 2) for p in parts]),
                          np.concatenate([np.asarray(p[1], np.uint8).reshape(-1, 32) for p in parts]),
                          np.concatenate([np.asarray(p[2], float).reshape(-1, 3) for p in parts]),
                          np.concatenate([np.asarray(p[3], bool).reshape(-1) for p in parts])))
        return vocab, ids[keep], rows[keep], feats

    def close(self) -> None:
        """Release the verification features (their temporary file); queries after this verify
        nothing (no candidate has features left)."""
        self._store.close()

    def _forget_beyond_cap(self) -> None:
        """Forget the oldest indexed keyframes beyond ``max_database_keyframes``. Positions in
        the bag-of-words database shift down, and so does the last loop's position."""
        while len(self._order) > self.config.max_database_keyframes:
            old = self._order.pop(0)
            self._store.forget(old)
            self._pending = [(k, d) for k, d in self._pending if k != old]
            if self._db is not None and len(self._db):
                self._db.forget_oldest()
                self._last_loop_at -= 1

    def _corner_features(self, uv, desc, camera, shape_hw, lm_uv, lm_xi, inv_depth_map, T_prevkf_kf,
                         prev) -> corner_mod.CornerFeatures:
        """Corners with 3-D points in keyframe units: triangulated against the previous keyframe
        (``points_geo``, what measures a loop), and for verification the network's depth in
        scale mode (many more corners), else the triangulated ones."""
        tri = np.full((len(uv), 3), np.nan)
        if prev is not None and prev[0] is not None and T_prevkf_kf is not None and len(uv):
            tri = corner_mod.triangulated_points(uv, desc, prev[0], prev[1], T_prevkf_kf, camera,
                                                 self.config.hamming_ratio)
        if inv_depth_map is None:
            return corner_mod.CornerFeatures(uv, desc, tri)
        pts = np.full((len(uv), 3), np.nan)
        size = (int(shape_hw[1]), int(shape_hw[0]))
        lm_uv = np.asarray(lm_uv, float).reshape(-1, 2)
        m_per_unit = corner_mod.metres_per_unit(lm_xi, sample_map(inv_depth_map, lm_uv, size))
        if m_per_unit is not None and len(uv):
            pts = corner_mod.network_points(uv, sample_map(inv_depth_map, uv, size), m_per_unit, camera)
        return corner_mod.CornerFeatures(uv, desc, pts, tri)
