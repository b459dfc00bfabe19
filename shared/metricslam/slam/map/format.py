"""The saved-map format (schema version 1): one directory, a JSON header and plain ``.npy`` arrays.

Layout (``docs/maps.md`` is the reference; frames and units per ``docs/conventions.md``)::

    MAP/header.json                 format, schema_version, camera, depth model id, vocabulary id,
                                    counts, and for every array file its sha256, bytes, dtype, shape
    MAP/keyframes/<name>.npy        N keyframes: kf_id, frame_index, t_ns, T_map_kf (metric,
                                    rigid), scale_kf (metres per keyframe VO unit), scale history
    MAP/landmarks/<name>.npy        L landmarks: map-frame position (m) and their observation
    MAP/loop_db/<name>.npy          the place-recognition database: vocabulary (K words, IDF),
                                    M bag-of-words rows, F verification features of those rows

Loading never executes code: JSON and ``numpy.load(allow_pickle=False)``. Each ``.npy`` file is
written by ``numpy.save`` (no timestamps), so saving a loaded map gives byte-identical files.
Every problem is a one-line :class:`~metricslam.errors.MapError` naming the file and what to do.
Saving is atomic: the map is written beside the target and swapped in by ``rename``; a failed
save leaves the previous map as it was.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.errors import MapError

FORMAT_NAME = "metricslam-map"
SCHEMA_VERSION = 1
HEADER = "header.json"

#: group -> array name -> (numpy dtype string, shape with symbolic sizes). N keyframes,
#: L landmarks, K vocabulary words, M bag-of-words rows, F features, M1 = M + 1.
SCHEMA: dict[str, dict[str, tuple[str, tuple]]] = {
    "keyframes": {
        "kf_id": ("<i8", ("N",)), "frame_index": ("<i8", ("N",)), "t_ns": ("<i8", ("N",)),
        "T_map_kf": ("<f8", ("N", 4, 4)), "scale_kf": ("<f8", ("N",)),
        "scale_live": ("<f8", ("N",)), "scale_factors": ("<i8", ("N",)),
        "scale_measured_median": ("<f8", ("N",)),
    },
    "landmarks": {
        "p_map_m": ("<f8", ("L", 3)), "obs_kf_id": ("<i8", ("L",)), "obs_uv_px": ("<f4", ("L", 2)),
    },
    "loop_db": {
        "vocabulary_words": ("|u1", ("K", 32)), "vocabulary_idf": ("<f4", ("K",)),
        "bow_kf_id": ("<i8", ("M",)), "bow_rows": ("<f4", ("M", "K")),
        "feature_offsets": ("<i8", ("M1",)), "feature_uv_px": ("<f4", ("F", 2)),
        "feature_points_kf_m": ("<f4", ("F", 3)), "feature_descriptors": ("|u1", ("F", 32)),
        "feature_exact": ("|b1", ("F",)),
    },
}


@dataclass(frozen=True)
class SavedMap:
    """A map in memory: ``arrays[group][name]`` as in :data:`SCHEMA`, plus its header fields.

    ``metric``: positions are metres (a learned-scale run); False for a ``--no-scale`` map,
    whose units are its first keyframe's VO units. ``source``: free-form JSON about how it was
    built (sequence, frames, mode); kept as is through load and save.
    """

    camera: PinholeCamera
    depth_model_id: str | None
    metric: bool
    arrays: dict[str, dict[str, np.ndarray]]
    source: dict = field(default_factory=dict)

    @property
    def n_keyframes(self) -> int:
        return int(len(self.arrays["keyframes"]["kf_id"]))

    @property
    def vocabulary_id(self) -> str:
        """sha256 (16 hex) of the vocabulary's words and IDF: which vocabulary the rows use."""
        db = self.arrays["loop_db"]
        h = hashlib.sha256(np.ascontiguousarray(db["vocabulary_words"]).tobytes())
        h.update(np.ascontiguousarray(db["vocabulary_idf"]).tobytes())
        return h.hexdigest()[:16]

    def check_fits(self, camera: PinholeCamera, depth_model_id: str | None, path: object = "map") -> None:
        """Raise :class:`MapError` when this session's camera or depth model is not the map's."""
        mine, theirs = self.camera.model_dump(), camera.model_dump()
        bad = [k for k in mine if not np.isclose(float(mine[k]), float(theirs[k]), rtol=1e-6, atol=1e-6)]
        if bad:
            raise MapError(f"map {path} was built with another camera ({', '.join(f'{k} {mine[k]} vs {theirs[k]}' for k in bad)}): "
                           "build a map with this camera, or pass the map's calibration with --calib")
        if self.depth_model_id != depth_model_id:
            raise MapError(f"map {path} was built with depth model {self.depth_model_id} but this run uses "
                           f"{depth_model_id}: use the same --model (and scale mode) as the map's session")


def _sizes(arrays: dict[str, dict[str, np.ndarray]]) -> dict[str, int]:
    kf, lm, db = arrays["keyframes"], arrays["landmarks"], arrays["loop_db"]
    m = len(db["bow_kf_id"])
    return {"N": len(kf["kf_id"]), "L": len(lm["p_map_m"]), "K": len(db["vocabulary_words"]),
            "M": m, "M1": m + 1, "F": len(db["feature_uv_px"])}


def _check_arrays(arrays: dict[str, dict[str, np.ndarray]], where: str) -> None:
    """Every array present with the schema's dtype and shape; sizes consistent across files."""
    for group, names in SCHEMA.items():
        for name in names:
            if name not in arrays.get(group, {}):
                raise MapError(f"{where}: array {group}/{name} is missing")
    sizes = _sizes(arrays)
    for group, names in SCHEMA.items():
        for name, (dtype, shape) in names.items():
            a = arrays[group][name]
            want = tuple(sizes[d] if isinstance(d, str) else d for d in shape)
            if a.dtype.str != dtype or a.shape != want:
                raise MapError(f"{where}: {group}/{name}.npy holds {a.dtype.str} {a.shape}, the schema "
                               f"wants {dtype} {want}: the map is corrupt or was edited; rebuild it")
    offsets = arrays["loop_db"]["feature_offsets"]
    if offsets[0] != 0 or offsets[-1] != sizes["F"] or np.any(np.diff(offsets) < 0):
        raise MapError(f"{where}: loop_db/feature_offsets do not index the {sizes['F']} features: "
                       "the map is corrupt; rebuild it")


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


def save_map(saved: SavedMap, path: str | Path) -> Path:
    """Write ``saved`` to the directory ``path`` atomically (module docstring).

    Raises:
        MapError: the arrays do not fit the schema, ``path`` is a file or a folder that is not
            a map, or it cannot be written.
    """
    target = Path(path)
    _check_arrays(saved.arrays, f"map {target}")
    if target.exists() and (not target.is_dir() or (any(target.iterdir()) and not (target / HEADER).is_file())):
        raise MapError(f"--save-map {target} exists and is not a map folder: name a new folder "
                       "(an existing map there is replaced atomically)")
    files: dict[str, dict] = {}
    blobs: dict[str, bytes] = {}
    for group, names in SCHEMA.items():
        for name in names:
            rel = f"{group}/{name}.npy"
            blob = _npy_bytes(saved.arrays[group][name])
            blobs[rel] = blob
            a = saved.arrays[group][name]
            files[rel] = {"sha256": hashlib.sha256(blob).hexdigest(), "bytes": len(blob),
                          "dtype": a.dtype.str, "shape": list(a.shape)}
    sizes = _sizes(saved.arrays)
    header = {"format": FORMAT_NAME, "schema_version": SCHEMA_VERSION, "frame": "map",
              "units": "m" if saved.metric else "first keyframe VO units", "metric": bool(saved.metric),
              "camera": saved.camera.model_dump(), "depth_model_id": saved.depth_model_id,
              "vocabulary_id": saved.vocabulary_id,
              "counts": {"keyframes": sizes["N"], "landmarks": sizes["L"], "words": sizes["K"],
                         "bow_rows": sizes["M"], "features": sizes["F"]},
              "source": saved.source, "files": files}
    tmp = target.parent / f".{target.name}.tmp-{os.getpid()}"
    old = target.parent / f".{target.name}.old-{os.getpid()}"
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(tmp, ignore_errors=True)
        for group in SCHEMA:
            (tmp / group).mkdir(parents=True)
        for rel, blob in blobs.items():
            _write_synced(tmp / rel, blob)
        _write_synced(tmp / HEADER, (json.dumps(header, indent=2, sort_keys=True) + "\n").encode())
        if target.exists():
            os.rename(target, old)
        os.rename(tmp, target)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if old.exists() and not target.exists():
            os.rename(old, target)  # put the previous map back
        raise MapError(f"cannot write map {target} ({exc.strerror or exc}): choose a folder you can "
                       "write to; any previous map there is unchanged") from exc
    shutil.rmtree(old, ignore_errors=True)
    return target


def _write_synced(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def read_header(path: str | Path) -> dict:
    """The parsed, checked ``header.json`` of the map at ``path`` (format and schema version)."""
    root = Path(path)
    if not root.exists():
        raise MapError(f"map {root} does not exist: give the folder written by --save-map")
    if not root.is_dir():
        raise MapError(f"map {root} is a file; a map is a folder (written by --save-map)")
    hp = root / HEADER
    if not hp.is_file():
        raise MapError(f"map {root} has no {HEADER}: not a metricslam map, or an interrupted copy")
    try:
        header = json.loads(hp.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapError(f"map {root}: {HEADER} is unreadable or not JSON ({exc}): the map is corrupt") from exc
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise MapError(f"map {root}: {HEADER} is not a {FORMAT_NAME} header")
    version = header.get("schema_version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise MapError(f"map {root}: schema_version {version!r} is not an integer: the header is corrupt")
    if version > SCHEMA_VERSION:
        raise MapError(f"map {root} has schema version {version}, newer than this metricslam reads "
                       f"({SCHEMA_VERSION}): upgrade metricslam")
    if version < SCHEMA_VERSION:
        raise MapError(f"map {root} has schema version {version}, which this metricslam no longer "
                       f"reads ({SCHEMA_VERSION}): rebuild the map with --save-map")
    return header


def load_map(path: str | Path) -> SavedMap:
    """Read and check the map at ``path`` (checksums, dtypes, shapes, counts, vocabulary id).

    Raises:
        MapError: one line naming the problem (missing folder or file, corrupt file, checksum
            mismatch, other schema version, inconsistent arrays).
    """
    root = Path(path)
    header = read_header(root)
    files = header.get("files")
    if not isinstance(files, dict):
        raise MapError(f"map {root}: {HEADER} lists no files: the header is corrupt")
    arrays: dict[str, dict[str, np.ndarray]] = {g: {} for g in SCHEMA}
    for group, names in SCHEMA.items():
        for name in names:
            rel = f"{group}/{name}.npy"
            entry = files.get(rel)
            if not isinstance(entry, dict) or "sha256" not in entry:
                raise MapError(f"map {root}: {HEADER} does not list {rel}: the header is corrupt")
            fp = root / rel
            try:
                blob = fp.read_bytes()
            except FileNotFoundError:
                raise MapError(f"map {root} is incomplete: {rel} is missing") from None
            except OSError as exc:
                raise MapError(f"map {root}: cannot read {rel} ({exc.strerror or exc})") from exc
            if hashlib.sha256(blob).hexdigest() != entry["sha256"]:
                raise MapError(f"map {root}: {rel} does not match its checksum in {HEADER} (corrupt "
                               "or truncated): restore the map or rebuild it")
            try:
                arrays[group][name] = np.load(io.BytesIO(blob), allow_pickle=False)
            except ValueError as exc:
                raise MapError(f"map {root}: {rel} is not a plain numeric array ({exc}); refused") from exc
    _check_arrays(arrays, f"map {root}")
    try:
        camera = PinholeCamera(**header["camera"])
    except Exception as exc:  # noqa: BLE001 -- pydantic's error, one line
        raise MapError(f"map {root}: the header's camera is invalid ({str(exc).splitlines()[0]})") from exc
    saved = SavedMap(camera, header.get("depth_model_id"), bool(header.get("metric", False)), arrays,
                     dict(header.get("source") or {}))
    if header.get("vocabulary_id") != saved.vocabulary_id:
        raise MapError(f"map {root}: the vocabulary does not match the header's vocabulary_id: corrupt map")
    return saved


def depth_model_id(model_path: str | Path | None) -> str | None:
    """The id a map records for the depth model it was built with: ``sha256:`` and the first 16
    hex of the ONNX file's sha256 (None: no learned scale)."""
    if model_path is None:
        return None
    try:
        return "sha256:" + hashlib.sha256(Path(model_path).read_bytes()).hexdigest()[:16]
    except OSError as exc:
        raise MapError(f"cannot read depth model {model_path} to identify it ({exc.strerror or exc})") from exc
