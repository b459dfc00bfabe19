"""Extending a loaded map: ``metricslam run SEQ --map MAP --save-map OUT`` (issue #34 item 2).

The rendered loop of ``test_map_relocalize`` (300 frames, seed 3): session 1 (frames 0-149)
saves ``map1``; session 2 (frames 190-299) relocalizes into it and saves the merged ``map2``;
session 3 (frames 200-249) drives road that only session 2 saw.

* save → load → extend → save: ``map2`` holds ``map1`` unchanged (its keyframes were fixed
  nodes; same vocabulary, same rows, same features) followed by session 2's keyframes with new
  ids, joined by cross-session factors; loading and saving ``map2`` again gives byte-identical
  files;
* the appended keyframes are usable: session 3 relocalizes into ``map2`` against them, sooner
  than into ``map1`` (where only a far view of map keyframe 0, near the loop's end, can match);
* extending a map in place (``--save-map`` the ``--map`` folder) replaces it atomically.
"""

from __future__ import annotations

import filecmp
import json

import numpy as np
import pytest
from bench.maps import cut as cut_sequence
from metricslam.slam.map.format import SCHEMA, load_map, save_map
from metricslam_cli.main import main

pytestmark = pytest.mark.slow


def _run(seq, out, *flags) -> tuple[int, dict]:
    code = main(["run", str(seq), "--out", str(out), "--json", str(out.with_suffix(".json")), "--deterministic",
                 "--no-progress", *map(str, flags)])
    return code, json.loads(out.with_suffix(".json").read_text())


@pytest.fixture(scope="module")
def maps(synth_sequence, tmp_path_factory):
    src = synth_sequence(300, seed=3, path="loop")
    root = tmp_path_factory.mktemp("extend")
    s1 = cut_sequence(src, root / "s1", 0, 150)
    s2 = cut_sequence(src, root / "s2", 190, 300)
    cut_sequence(src, root / "s3", 200, 250)
    assert _run(s1, root / "s1.txt", "--save-map", root / "map1")[0] == 0
    code, stats = _run(s2, root / "s2.txt", "--map", root / "map1", "--save-map", root / "map2")
    assert code == 0 and stats["map"]["relocalized"], stats.get("map")
    return root, stats


def test_extended_map_keeps_the_loaded_one_and_round_trips(maps, tmp_path):
    root, stats = maps
    map1, map2 = load_map(root / "map1"), load_map(root / "map2")
    ext = stats["map_saved"]["extended"]
    assert ext["cross_session_factors"] >= 2 and ext["map_keyframes_fixed"] >= 1, ext
    assert ext["graph_error_after"] <= ext["graph_error_before"], ext
    n1, n2 = map1.n_keyframes, map2.n_keyframes
    assert n2 == n1 + ext["session_keyframes"] == stats["map_saved"]["keyframes"]
    sizes1 = {"keyframes": n1, "landmarks": len(map1.arrays["landmarks"]["p_map_m"]),
              "loop_db": len(map1.arrays["loop_db"]["bow_kf_id"])}
    for group, names in SCHEMA.items():
        for name in names:
            a, b = map1.arrays[group][name], map2.arrays[group][name]
            if name in ("vocabulary_words", "vocabulary_idf"):
                np.testing.assert_array_equal(a, b)
            elif name.startswith("feature_") and name != "feature_offsets":
                np.testing.assert_array_equal(a, b[:len(a)], err_msg=name)
            else:
                np.testing.assert_array_equal(a, b[:sizes1[group] + (name == "feature_offsets")], err_msg=name)
    new_ids = map2.arrays["keyframes"]["kf_id"][n1:]
    assert new_ids.min() > map1.arrays["keyframes"]["kf_id"].max() and len(set(new_ids)) == len(new_ids)
    assert len(map2.arrays["loop_db"]["bow_kf_id"]) > sizes1["loop_db"]  # appended rows, map vocabulary
    assert map2.vocabulary_id == map1.vocabulary_id
    assert map2.source["extended_by"][0]["sequence"] == str(root / "s2")
    save_map(load_map(root / "map2"), tmp_path / "again")
    for rel in json.loads((root / "map2" / "header.json").read_text())["files"]:
        assert filecmp.cmp(root / "map2" / rel, tmp_path / "again" / rel, shallow=False), rel
    assert filecmp.cmp(root / "map2" / "header.json", tmp_path / "again" / "header.json", shallow=False)


def test_appended_keyframes_relocalize_a_later_session(maps):
    root, _ = maps
    n1 = load_map(root / "map1").n_keyframes
    first_id = int(load_map(root / "map2").arrays["keyframes"]["kf_id"][n1])
    code2, st2 = _run(root / "s3", root / "s3_map2.txt", "--map", root / "map2")
    assert code2 == 0 and st2["map"]["relocalized"], st2["map"]
    matched_ids = [m[1] for m in st2["map"]["matched_frames"]]
    assert min(matched_ids) >= first_id, matched_ids  # only session 2's keyframes cover this road
    code1, st1 = _run(root / "s3", root / "s3_map1.txt", "--map", root / "map1")
    if code1 == 0:
        assert st1["map"]["first_localized_frame"] > st2["map"]["first_localized_frame"] + 10, (st1["map"], st2["map"])
    # extend in place: the folder is replaced atomically by the merged map
    before = load_map(root / "map2").n_keyframes
    code, st = _run(root / "s3", root / "s3_again.txt", "--map", root / "map2", "--save-map", root / "map2")
    assert code == 0 and load_map(root / "map2").n_keyframes == before + st["map_saved"]["extended"]["session_keyframes"]
