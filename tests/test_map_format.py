"""The saved-map format (docs/maps.md): round trips exactly, and every bad map is a clear error.

Properties, over seeded random maps of varied sizes (including empty landmark and feature sets):
save → load gives identical arrays (values, dtypes, shapes) and header fields; load → save writes
byte-identical files. A corrupted file, a missing file, a future or past schema version, a
pickled array, a non-map folder, another camera or depth model each raise one
:class:`~metricslam.errors.MapError` that names the problem.
"""

from __future__ import annotations

import filecmp
import hashlib
import json

import numpy as np
import pytest
from metricslam.camera import PinholeCamera
from metricslam.errors import MapError, MetricSlamError
from metricslam.slam.map.format import SCHEMA, SavedMap, load_map, save_map

CAMERA = PinholeCamera(fx_px=359.1, fy_px=359.1, cx_px=303.1, cy_px=92.4, width_px=620, height_px=188)


def random_map(seed: int, n_kf: int = 7, words: int = 16) -> SavedMap:
    """A schema-valid map of random content (``n_kf`` keyframes, half of them indexed)."""
    rng = np.random.default_rng(seed)
    rows = n_kf // 2
    per_row = rng.integers(0, 20, rows)
    f = int(per_row.sum())
    sizes = {"N": n_kf, "L": f, "K": words, "M": rows, "M1": rows + 1, "F": f}
    arrays: dict[str, dict[str, np.ndarray]] = {}
    for group, names in SCHEMA.items():
        arrays[group] = {}
        for name, (dtype, shape) in names.items():
            shp = tuple(sizes[d] if isinstance(d, str) else d for d in shape)
            dt = np.dtype(dtype)
            if dt.kind == "f":
                a = rng.normal(size=shp).astype(dt)
            elif dt.kind == "b":
                a = rng.random(shp) < 0.5
            else:
                a = rng.integers(0, 255 if dt.itemsize == 1 else 10**9, shp).astype(dt)
            arrays[group][name] = a
    arrays["loop_db"]["feature_offsets"] = np.concatenate([[0], np.cumsum(per_row)]).astype(np.int64)
    arrays["keyframes"]["scale_measured_median"][0] = np.nan  # no measurement: NaN survives
    return SavedMap(CAMERA, "sha256:0123456789abcdef", True, arrays, {"sequence": f"seed{seed}"})


@pytest.mark.parametrize("seed,n_kf", [(0, 7), (1, 1), (2, 40), (3, 2)])
def test_round_trip_is_exact(tmp_path, seed, n_kf):
    saved = random_map(seed, n_kf)
    save_map(saved, tmp_path / "a")
    loaded = load_map(tmp_path / "a")
    for group, names in SCHEMA.items():
        for name in names:
            a, b = saved.arrays[group][name], loaded.arrays[group][name]
            assert a.dtype == b.dtype and a.shape == b.shape, (group, name)
            np.testing.assert_array_equal(a, b)
    assert (loaded.camera, loaded.depth_model_id, loaded.metric, loaded.source) == (
        saved.camera, saved.depth_model_id, saved.metric, saved.source)
    save_map(loaded, tmp_path / "b")
    cmp = filecmp.dircmp(tmp_path / "a", tmp_path / "b")
    files = ["header.json"] + [f"{g}/{n}.npy" for g, names in SCHEMA.items() for n in names]
    match, mismatch, errors = filecmp.cmpfiles(tmp_path / "a", tmp_path / "b", files, shallow=False)
    assert not mismatch and not errors and len(match) == len(files), (mismatch, errors, cmp.diff_files)


def test_save_replaces_a_map_atomically_and_keeps_it_on_failure(tmp_path):
    save_map(random_map(0), tmp_path / "m")
    before = (tmp_path / "m" / "header.json").read_bytes()
    bad = random_map(1)
    bad.arrays["keyframes"]["t_ns"] = bad.arrays["keyframes"]["t_ns"][:-1]  # wrong shape
    with pytest.raises(MapError, match="t_ns"):
        save_map(bad, tmp_path / "m")
    assert (tmp_path / "m" / "header.json").read_bytes() == before
    save_map(random_map(2), tmp_path / "m")
    assert load_map(tmp_path / "m").source == {"sequence": "seed2"}
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries left


def test_save_refuses_a_folder_that_is_not_a_map(tmp_path):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.jpg").write_bytes(b"x")
    with pytest.raises(MapError, match="not a map folder"):
        save_map(random_map(0), tmp_path / "photos")
    assert (tmp_path / "photos" / "a.jpg").exists()


def _edit_header(path, **changes):
    h = json.loads((path / "header.json").read_text())
    h.update(changes)
    (path / "header.json").write_text(json.dumps(h))


@pytest.fixture()
def saved_dir(tmp_path):
    return save_map(random_map(4), tmp_path / "map")


def test_corrupt_file_is_named(saved_dir):
    p = saved_dir / "keyframes" / "T_map_kf.npy"
    blob = bytearray(p.read_bytes())
    blob[-1] ^= 0xFF
    p.write_bytes(bytes(blob))
    with pytest.raises(MapError, match=r"keyframes/T_map_kf.npy does not match its checksum"):
        load_map(saved_dir)


def test_truncated_file_is_named(saved_dir):
    p = saved_dir / "loop_db" / "bow_rows.npy"
    p.write_bytes(p.read_bytes()[:40])
    with pytest.raises(MapError, match="loop_db/bow_rows.npy"):
        load_map(saved_dir)


def test_missing_file_is_named(saved_dir):
    (saved_dir / "landmarks" / "p_map_m.npy").unlink()
    with pytest.raises(MapError, match=r"incomplete: landmarks/p_map_m.npy is missing"):
        load_map(saved_dir)


@pytest.mark.parametrize("version,words", [(2, "newer than this metricslam reads"),
                                           (0, "no longer reads"), ("1", "not an integer")])
def test_other_schema_versions_are_refused(saved_dir, version, words):
    _edit_header(saved_dir, schema_version=version)
    with pytest.raises(MapError, match=words):
        load_map(saved_dir)


@pytest.mark.parametrize("make,words", [
    (lambda d: None, "does not exist"),
    (lambda d: d.write_text("x"), "is a file"),
    (lambda d: d.mkdir(), "no header.json"),
])
def test_not_a_map(tmp_path, make, words):
    target = tmp_path / "nomap"
    make(target)
    with pytest.raises(MapError, match=words):
        load_map(target)


def test_header_not_json(saved_dir):
    (saved_dir / "header.json").write_text("{not json")
    with pytest.raises(MapError, match="not JSON"):
        load_map(saved_dir)


def test_pickled_array_is_refused_not_run(saved_dir):
    """An object array with a valid checksum still never reaches pickle."""
    p = saved_dir / "keyframes" / "kf_id.npy"
    np.save(p, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    h = json.loads((saved_dir / "header.json").read_text())
    h["files"]["keyframes/kf_id.npy"]["sha256"] = hashlib.sha256(p.read_bytes()).hexdigest()
    (saved_dir / "header.json").write_text(json.dumps(h))
    with pytest.raises(MapError, match="not a plain numeric array"):
        load_map(saved_dir)


def test_another_camera_or_depth_model_is_refused(saved_dir):
    saved = load_map(saved_dir)
    saved.check_fits(CAMERA, "sha256:0123456789abcdef")
    other = CAMERA.model_copy(update={"fx_px": 400.0})
    with pytest.raises(MapError, match="another camera.*fx_px"):
        saved.check_fits(other, "sha256:0123456789abcdef")
    with pytest.raises(MapError, match="depth model"):
        saved.check_fits(CAMERA, "sha256:ffffffffffffffff")
    assert issubclass(MapError, MetricSlamError)


@pytest.fixture()
def tiny_sequence(synth_sequence):
    return synth_sequence(3, seed=1, path="straight", size=(160, 64))


def test_run_with_a_bad_map_fails_before_the_first_frame(tiny_sequence, tmp_path, capsys):
    """``run --map`` checks the map (and ``--save-map`` the target) before any frame: one line."""
    from metricslam_cli.main import main

    out = str(tmp_path / "est.txt")
    (tmp_path / "file").write_text("x")
    cases = [(["--map", str(tmp_path / "absent")], "does not exist"),
             (["--save-map", str(tmp_path / "file")], "is a file"),
             (["--map", str(tmp_path / "a"), "--save-map", str(tmp_path / "b")], "does not exist")]
    for flags, words in cases:
        assert main(["run", str(tiny_sequence), "--out", out, "--no-progress", "--deterministic", *flags]) == 1
        err = capsys.readouterr().err.strip()
        assert words in err and len(err.splitlines()) == 1, err
        assert not (tmp_path / "est.txt").exists() or (tmp_path / "est.txt").read_text() == ""
