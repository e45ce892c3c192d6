"""Readers/writers of the thesis formats (torchhand.io.thesis) and model assets
(torchhand.io.assets): bad input on a tiny synthetic model, and the real data."""

from __future__ import annotations

import numpy as np
import pytest

from torchhand.io import (
    FormatError,
    ModelAssets,
    assets_from_thesis,
    available_models,
    find_model,
    load_assets,
    read_calibration,
    read_index_bounds,
    read_limits,
    read_models_info,
    read_motion,
    read_off,
    read_skel,
    read_skin,
    read_thesis_model,
    read_voi,
    read_zones,
    save_assets,
    sequence_models,
    write_motion,
)


def _assert_motion_round_trip(motion, path) -> None:
    """write_motion then read_motion gives the same bones, in order, to 1e-6."""
    write_motion(path, motion)
    back = read_motion(path)
    assert list(back) == list(motion)
    for b in motion:
        np.testing.assert_allclose(back[b], motion[b], rtol=0, atol=1e-6)


def _names_file_and_line(err: pytest.ExceptionInfo, path, line: int | None = None) -> None:
    msg = str(err.value)
    assert str(path) in msg, f"message does not name the file: {msg}"
    if line is not None:
        assert f"line {line}" in msg, f"message does not name line {line}: {msg}"


# ====================================================== the tiny valid model
def test_tiny_thesis_model_reads_back_exactly(tmp_thesis_model):
    t = tmp_thesis_model
    files = read_thesis_model(t.dir, t.name)
    np.testing.assert_array_equal(files.mesh.vertices, t.vertices)
    np.testing.assert_array_equal(files.mesh.faces, t.faces)
    assert files.mesh.faces.dtype == np.int64
    assert files.skeleton.num_motion_rows == t.num_motion_rows
    assert [c for _, c, _ in files.skeleton.bones] == t.bone_names
    assert [l for _, _, l in files.skeleton.bones] == t.lengths
    assert files.skin.bone_names == t.bone_names
    np.testing.assert_array_equal(files.skin.weights, t.weights)
    assert list(files.limits) == t.bone_names
    assert files.limits["Root"].translation and not files.limits["B1"].translation
    assert files.limits["B1"].rotation == (False, True, True)
    np.testing.assert_array_equal(files.limits["B2"].limits_deg[2], [-90, 45])
    assert files.zones.names == ["Root", "B"]
    np.testing.assert_array_equal(files.zones.thresholds, [0.5, 1.0])
    assert files.voi is None  # objects have no VOI
    assert list(files.motion) == t.bone_names
    for b in t.bone_names:
        np.testing.assert_allclose(files.motion[b], t.motion[b], atol=1e-7)


def test_tiny_thesis_model_builds_assets_with_expected_dofs(tmp_thesis_model):
    t = tmp_thesis_model
    assets = assets_from_thesis(read_thesis_model(t.dir, t.name))
    assert assets.kind == "object" and assets.side is None
    assert assets.name == t.name  # not a known thesis name: kept as is
    assert assets.bone_names == t.bone_names
    np.testing.assert_array_equal(assets.parents, [-1, 0, 1])
    assert assets.dof_names == ["root:tx", "root:ty", "root:tz", "root:rx", "root:ry", "root:rz",
                                "B1:y", "B1:z", "B2:z"]
    np.testing.assert_allclose(assets.slot_limits[1, 1], np.deg2rad([-45, 30]))
    np.testing.assert_allclose(assets.slot_limits[2, 2], np.deg2rad([-90, 45]))
    np.testing.assert_allclose(assets.rest_transforms, np.stack([t.motion[b][0] for b in t.bone_names]), atol=1e-9)
    np.testing.assert_allclose(assets.skin_weight.sum(1), 1.0, atol=1e-12)


def test_save_and_load_assets_round_trip(tmp_thesis_model, tmp_path):
    t = tmp_thesis_model
    assets = assets_from_thesis(read_thesis_model(t.dir, t.name), source="tiny")
    path = save_assets(assets, tmp_path / "tiny.npz")
    back = load_assets(path)
    assert isinstance(back, ModelAssets)
    for k in ("vertices", "faces", "skin_index", "skin_weight", "parents", "rest_transforms",
              "bone_lengths", "slot_axes", "slot_used", "slot_limits"):
        np.testing.assert_array_equal(getattr(back, k), getattr(assets, k), err_msg=k)
    assert back.bone_names == assets.bone_names and back.zones == assets.zones
    assert back.source == "tiny" and back.dof_names == assets.dof_names
    # A second save without overwrite refuses and leaves the file alone.
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="overwrite"):
        save_assets(assets, path)
    assert path.read_bytes() == before


def test_find_model_unknown_name_raises_lookup_error_listing_models():
    with pytest.raises(LookupError) as err:
        find_model("no_such_model")
    msg = str(err.value)
    assert "no_such_model" in msg
    for name in ("hand_right", "hand_left", "rope"):
        assert name in msg
    assert set(available_models()) >= {"hand_right", "hand_left", "ball", "cube", "pipe", "rope"}


def test_find_model_missing_npz_path_raises_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        find_model(str(tmp_path / "missing.npz"))


# ================================================================ bad input
def test_missing_file_raises_format_error_naming_it(tmp_path):
    path = tmp_path / "nothing.OFF"
    with pytest.raises(FormatError, match="file not found") as err:
        read_off(path)
    _names_file_and_line(err, path)


def test_missing_model_lists_models_in_folder(tmp_thesis_model):
    t = tmp_thesis_model
    with pytest.raises(FormatError, match="file not found") as err:
        read_thesis_model(t.dir, "Model_Hand_X")
    _names_file_and_line(err, t.dir / "Model_Hand_X.OFF")
    assert t.name in str(err.value)  # lists the models that are there


def test_missing_skin_file_is_named(tmp_thesis_model):
    t = tmp_thesis_model
    t.path("SKIN").unlink()
    with pytest.raises(FormatError, match="file not found") as err:
        read_thesis_model(t.dir, t.name)
    _names_file_and_line(err, t.path("SKIN"))


def test_truncated_off_fewer_vertices_than_header(tmp_thesis_model):
    t = tmp_thesis_model
    lines = t.lines["OFF"]
    n_v = len(t.vertices)
    # drop the last 3 vertex lines: the header still promises n_v vertices
    path = t.rewrite("OFF", lines[: 2 + n_v - 3] + lines[2 + n_v :])
    with pytest.raises(FormatError, match="truncated") as err:
        read_off(path)
    _names_file_and_line(err, path)
    assert f"{n_v} vertices" in str(err.value)


def test_truncated_motion_one_bone_with_fewer_rows(tmp_thesis_model):
    t = tmp_thesis_model
    lines = list(t.lines["MOTION"])
    # bone B1 is lines [N+1 .. 2N+1]; drop its last row
    n = t.num_motion_rows
    b1 = lines.index("B1")
    del lines[b1 + n]
    path = t.rewrite("MOTION", lines)
    with pytest.raises(FormatError, match="different numbers of rows") as err:
        read_motion(path)
    _names_file_and_line(err, path)
    assert "'B1': 2" in str(err.value)


def test_motion_rows_before_any_bone_name_report_the_missing_name(tmp_thesis_model):
    t = tmp_thesis_model
    lines = list(t.lines["MOTION"])
    path = t.rewrite("MOTION", lines[1:])  # drop the first bone name: line 1 is now a row
    with pytest.raises(FormatError) as err:
        read_motion(path)
    _names_file_and_line(err, path, 1)
    assert "got 12" not in str(err.value) and "name" in str(err.value)


def test_skin_row_count_differs_from_off_vertex_count(tmp_thesis_model):
    t = tmp_thesis_model
    t.rewrite("SKIN", t.lines["SKIN"][:-2])  # 2 rows fewer than the mesh has vertices
    with pytest.raises(FormatError) as err:
        read_thesis_model(t.dir, t.name)
    _names_file_and_line(err, t.path("SKIN"))
    msg = str(err.value)
    assert f"{len(t.vertices) - 2} weight rows" in msg and f"{len(t.vertices)} vertices" in msg


# One line of a file replaced: (file, 0-based line, new text or f(old text), reader,
# expected message, 1-based line the message must name).
ONE_LINE_ERRORS = [
    ("MOTION", 2, lambda old: " ".join(old.split()[:11]), lambda p, t: read_motion(p), "expected 12 numbers", 3),
    ("SKIN", 7, "0.5000 0.2000 0.0000 ", lambda p, t: read_skin(p, num_vertices=len(t.vertices)),
     r"vertex 5 sum to 0\.7000, expected 1", 8),
    ("SKIN", 6, "1.2000 -0.2000 0.0000 ", lambda p, t: read_skin(p), "negative skinning weight for vertex 4", 7),
    ("SKIN", 1, "Root B1", lambda p, t: read_skin(p), "expected 3 bone names, got 2", 2),
    ("SKEL", 0, "many", lambda p, t: read_skel(p), "number of motion rows", 1),
]


@pytest.mark.parametrize("kind, index, text, reader, match, line", ONE_LINE_ERRORS,
                         ids=["motion-row-length", "skin-sum", "skin-negative", "skin-bone-names", "skel-header"])
def test_a_bad_line_gives_an_error_naming_file_and_line(tmp_thesis_model, kind, index, text, reader, match, line):
    t = tmp_thesis_model
    lines = list(t.lines[kind])
    lines[index] = text(lines[index]) if callable(text) else text
    path = t.rewrite(kind, lines)
    with pytest.raises(FormatError, match=match) as err:
        reader(path, t)
    _names_file_and_line(err, path, line)


def test_non_numeric_token_in_limits_names_line(tmp_thesis_model):
    t = tmp_thesis_model
    lines = list(t.lines["LIMITS"])
    i = lines.index("B1") + 6  # the rot-y range "-45 30"
    lines[i] = "-45 thirty"
    path = t.rewrite("LIMITS", lines)
    with pytest.raises(FormatError, match="expected numbers") as err:
        read_limits(path)
    _names_file_and_line(err, path, i + 1)
    assert "thirty" in str(err.value)


def test_limits_block_with_missing_line_names_bone(tmp_thesis_model):
    t = tmp_thesis_model
    lines = list(t.lines["LIMITS"])
    i = lines.index("B2")
    del lines[i + 7]  # drop the last range row of B2
    path = t.rewrite("LIMITS", lines)
    with pytest.raises(FormatError, match="'B2' has 7 lines, expected 8") as err:
        read_limits(path)
    _names_file_and_line(err, path, i + 1)


def test_off_face_id_out_of_range(tmp_thesis_model):
    t = tmp_thesis_model
    lines = list(t.lines["OFF"])
    lines[-1] = f"3 0 1 {len(t.vertices)}"
    path = t.rewrite("OFF", lines)
    # reported either by the reader's own check or by trimesh's parser
    with pytest.raises(FormatError, match=r"face .*(range|ids)") as err:
        read_off(path)
    _names_file_and_line(err, path)


def test_motion_missing_a_skinning_bone(tmp_thesis_model):
    t = tmp_thesis_model
    lines = list(t.lines["MOTION"])
    b2 = lines.index("B2")
    t.rewrite("MOTION", lines[:b2])
    with pytest.raises(FormatError, match=r"no rows for skinning bones \['B2'\]") as err:
        read_thesis_model(t.dir, t.name)
    _names_file_and_line(err, t.path("MOTION"))


def test_write_motion_refuses_existing_file_and_leaves_it_unchanged(tmp_thesis_model):
    t = tmp_thesis_model
    path = t.path("MOTION")
    before = path.read_bytes()
    other = {b: np.tile(np.eye(4), (2, 1, 1)) for b in t.bone_names}
    with pytest.raises(FileExistsError) as err:
        write_motion(path, other)
    assert str(path) in str(err.value) and "overwrite" in str(err.value)
    assert path.read_bytes() == before
    write_motion(path, other, overwrite=True)
    assert read_motion(path)["B1"].shape == (2, 4, 4)


def test_write_motion_rejects_inconsistent_and_non_finite_input(tmp_path):
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        write_motion(tmp_path / "a.MOTION", {"A": np.zeros((2, 4, 4)), "B": np.zeros((3, 4, 4))})
    bad = np.tile(np.eye(4), (2, 1, 1))
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="'A' contains NaN"):
        write_motion(tmp_path / "b.MOTION", {"A": bad})
    assert not (tmp_path / "a.MOTION").exists() and not (tmp_path / "b.MOTION").exists()


def test_write_read_motion_round_trip_random_transforms(tmp_path):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    motion = {}
    for b in ("Lower Arm R", "RFing.0_Hand", "RFing.0_0"):  # a name with spaces too
        M = np.tile(np.eye(4), (7, 1, 1))
        M[:, :3, :3] = Rotation.random(7, random_state=rng).as_matrix()
        M[:, :3, 3] = rng.uniform(-900, 900, (7, 3))
        motion[b] = M
    _assert_motion_round_trip(motion, tmp_path / "x.MOTION")


# ================================================================ real data
def test_hand_off_has_10002_vertices_and_20000_faces(hia_root):
    mesh = read_off(hia_root / "Models" / "01" / "Model_Hand_R.OFF")
    assert mesh.vertices.shape == (10002, 3) and mesh.faces.shape == (20000, 3)
    assert mesh.faces.min() >= 0 and mesh.faces.max() < 10002


def test_right_hand_skel_has_20_bones(hia_root):
    skel = read_skel(hia_root / "Models" / "01" / "Model_Hand_R.SKEL")
    assert len(skel.bones) == 20
    assert skel.bones[0][1] == "Lower Arm R"  # the bone name with spaces is one line
    assert all(length > 0 for _, _, length in skel.bones)


@pytest.mark.parametrize("name", ["Model_Hand_R", "Model_Hand_L"])
def test_limits_flags_give_31_revolute_dofs_per_hand(hia_root, name):
    limits = read_limits(hia_root / "Models" / "01" / f"{name}.LIMITS")
    assert len(limits) == 20
    roots = [b for b, l in limits.items() if l.translation]
    assert len(roots) == 1 and roots[0].startswith("Lower Arm")
    revolute = sum(sum(l.rotation) for l in limits.values() if not l.translation)
    assert revolute == 31


def test_read_motion_rows_match_skel_first_line(hia_root, real_right_hand):
    skel = read_skel(hia_root / "Models" / "01" / "Model_Hand_R.SKEL")
    motion = real_right_hand.motion
    assert set(motion) == {c for _, c, _ in skel.bones}
    for b, M in motion.items():
        assert M.shape == (skel.num_motion_rows, 4, 4), b
        np.testing.assert_array_equal(M[:, 3], np.broadcast_to([0, 0, 0, 1.0], (len(M), 4)))
        # 6-digit rotations: orthonormal to ~1e-5
        RtR = np.einsum("nji,njk->nik", M[:, :3, :3], M[:, :3, :3])
        assert np.abs(RtR - np.eye(3)).max() < 1e-4


def test_write_read_motion_round_trip_real_motion(real_right_hand, tmp_path):
    _assert_motion_round_trip(real_right_hand.motion, tmp_path / "copy.MOTION")


def test_camera_intrinsics(hia_root):
    cams = read_calibration(hia_root / "Calibration" / "Cameras.txt")
    assert len(cams) == 1
    K = cams[0].K
    assert (K[0, 0], K[1, 1], K[0, 2], K[1, 2]) == (525.0, 525.0, 319.5, 239.5)
    assert K[0, 1] == 0 and np.array_equal(K[2], [0, 0, 1])
    np.testing.assert_array_equal(cams[0].Rt, np.eye(3, 4))
    assert cams[0].scale == 1.0


def test_models_info_of_sequence_18_lists_three_models(hia_root):
    names = read_models_info(hia_root / "Configs" / "18" / "MODELS_INFO.txt")
    assert names == ["Model_Hand_R", "Model_Hand_L", "Model_Object_Pipe_Green_Long"]
    names2, bounds = sequence_models(hia_root, "18")
    assert names2 == names
    assert bounds.motion_offset == 1 and bounds.total_aligned > 0


def test_index_bounds_of_sequence_01_fit_its_motion(hia_root):
    bounds = read_index_bounds(hia_root / "Configs" / "01" / "INDEX_BOUNDS.txt")
    skel = read_skel(hia_root / "Models" / "01" / "Model_Hand_R.SKEL")
    assert (bounds.motion_offset, bounds.video_offset) == (1, 0)
    # video frame k uses motion row k + 1; the last one must exist
    assert bounds.total_aligned - 1 + bounds.motion_offset < skel.num_motion_rows


def test_hand_voi_and_zones(hia_root):
    d = hia_root / "Models" / "01"
    voi = read_voi(d / "Model_Hand_R.VOI")
    assert all(len(g) == 5 for g in voi) and len(voi) >= 1
    assert all(0 <= g.min() and g.max() < 10002 for g in voi)
    zones = read_zones(d / "Model_Hand_R.ZONES")
    assert zones.names == ["Lower Arm", "_Hand", "_0", "_1", "_2"]
    assert zones.thresholds.shape == (5,)
    tips = read_voi(hia_root / "VOIs" / "VOIs_Model_0.txt")
    assert len(tips) == 5 and all(len(g) > 10 for g in tips)


def test_real_right_hand_assets_match_shipped_model(real_right_hand, model64):
    assets = assets_from_thesis(real_right_hand)
    shipped = model64("hand_right").assets
    assert assets.bone_names == shipped.bone_names
    np.testing.assert_array_equal(assets.vertices, shipped.vertices)
    # the rotations are re-orthonormalised in float64: numpy releases differ in the last bit
    np.testing.assert_allclose(assets.rest_transforms, shipped.rest_transforms, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(assets.slot_used, shipped.slot_used)
    assert len(assets.dof_names) == 37
