"""One patient frame (issue 15, item 7): the geometry of DICOM (LPS), NIfTI (RAS) and NRRD (its named space) is
kept in LPS as the store's `orientation`, with the origin written so that world positions are the patient's,
rotated onto the array axes. With `orient="LPS"` ingest also turns the array, by permutations and flips only, so
that world +x, +y, +z point left, posterior, superior: checked against nibabel's own reorientation
(io_orientation / apply_orientation) on random orientations; a DICOM CT and a NIfTI MR then show the face at
azimuth 0 alike. Named views put the eye on the same side of the patient with or without turning."""
from __future__ import annotations

import glob
import os
import tempfile

import nibabel as nib
import nrrd
import numpy as np
import pytest
from nibabel.orientations import apply_orientation, inv_ornt_aff, io_orientation

import lodcast
from lodcast.errors import SourceError
from lodcast.renderer.scene.camera import resolve_view
from lodcast.renderer.scene.scene import OrbitCamera, SceneError
from lodcast.store.orientation import axis_codes, legacy_axis_codes, view_direction
from lodcast.store.readers import open_source

RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


def reference(data_xyz: np.ndarray, affine_lps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """nibabel's closest canonical orientation of (x, y, z) data in LPS: the (z, y, x) array and its affine."""
    ornt = io_orientation(affine_lps)
    return apply_orientation(data_xyz, ornt).transpose(2, 1, 0), affine_lps @ inv_ornt_aff(ornt, data_xyz.shape)


def random_affine(rng: np.random.Generator, spacing: np.ndarray) -> np.ndarray:
    """An LPS affine: a random signed permutation of the axes tilted by up to 20° about a random axis."""
    perm = np.eye(3)[rng.permutation(3)] * rng.choice([-1.0, 1.0], 3)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(0, 20))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    tilt = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k  # Rodrigues
    a = np.eye(4)
    a[:3, :3] = tilt @ perm @ np.diag(spacing)
    a[:3, 3] = rng.uniform(-200, 200, 3)
    return a


def assert_like(src, expected: np.ndarray, affine: np.ndarray) -> None:
    np.testing.assert_array_equal(src.read(0, src.info.shape[0]), expected)
    steps = np.linalg.norm(affine[:3, :3], axis=0)
    direction = (affine[:3, :3] / steps).T
    np.testing.assert_allclose(src.info.spacing, steps[::-1], rtol=1e-6)
    np.testing.assert_allclose(src.info.origin, (direction @ affine[:3, 3])[::-1], atol=1e-3)
    np.testing.assert_allclose(src.info.direction, direction, atol=1e-5)
    assert src.info.space == "LPS" and np.all(np.diag(src.info.direction) > 0.9)


@pytest.mark.parametrize("seed", range(8))
def test_random_orientations_turn_as_nibabel_does(tmp_path, seed):
    """NIfTI (RAS, plain and gzip: the slab axis may move, so the source is copied once) and NRRD (LPS) of the
    same random geometry give nibabel's reoriented array, spacing, origin and residual direction."""
    rng = np.random.default_rng(seed)
    data = rng.integers(0, 60000, rng.integers(3, 9, 3)).astype(np.uint16)  # (x, y, z)
    lps = random_affine(rng, rng.uniform(0.3, 2.0, 3))
    expected, affine = reference(data, lps)
    nib.save(nib.Nifti1Image(data, RAS_TO_LPS @ lps), str(tmp_path / "v.nii"))
    nib.save(nib.Nifti1Image(data, RAS_TO_LPS @ lps), str(tmp_path / "v.nii.gz"))
    nrrd.write(str(tmp_path / "v.nrrd"), data, {"space": "left-posterior-superior",
                                                "space directions": lps[:3, :3].T, "space origin": lps[:3, 3]})
    with open_source(tmp_path / "v.nii", orient="source") as src:  # the file's axes, the geometry rigid around them
        np.testing.assert_array_equal(src.read(0, src.info.shape[0]), data.transpose(2, 1, 0))
        index = rng.integers(0, data.shape, size=(5, 3))  # (x, y, z)
        world = np.asarray(src.info.origin[::-1]) + index * src.info.spacing[::-1]
        patient = world @ np.asarray(src.info.direction)  # directionᵀ · world, row by row
        np.testing.assert_allclose(patient, index @ lps[:3, :3].T + lps[:3, 3], atol=1e-6)
        assert src.info.provenance.get("reoriented") is None
    before = set(glob.glob(os.path.join(tempfile.gettempdir(), "lodcast-reorient-*")))
    for name in ("v.nii", "v.nii.gz", "v.nrrd"):
        with open_source(tmp_path / name) as src:  # turned to LPS by default
            assert_like(src, expected, affine)
            np.testing.assert_array_equal(src.read(1, 2), expected[1:2])  # a slab again, out of order
    assert set(glob.glob(os.path.join(tempfile.gettempdir(), "lodcast-reorient-*"))) == before  # copies removed


def test_sagittal_dicom_series_is_stored_in_lps(tmp_path, capsys):
    """Sagittal slices (rows along +y, columns along −z, the normal towards the right): stored with x left, y
    posterior, z superior, as nibabel turns the same geometry; `lodcast info` says so."""
    from test_readers import dicom_slice

    rng = np.random.default_rng(3)
    stored = rng.integers(0, 4096, (5, 16, 12)).astype(np.uint16)  # (slice, row, column)
    (tmp_path / "sag").mkdir()
    for k in range(5):  # positions along the normal ascend with k; the names do not
        dicom_slice(tmp_path / "sag" / f"IM{9 - k}", stored[k], 0.0, intercept=0.0, orientation=(0, 1, 0, 0, 0, -1),
                    position=(10.0 - 2.0 * k, -20.0, 30.0))
    lps = np.eye(4)
    lps[:3, :3] = np.column_stack([[0, 0.25, 0], [0, 0, -0.5], [-2.0, 0, 0]])  # columns, rows, slices
    lps[:3, 3] = [10.0, -20.0, 30.0]
    expected, affine = reference(stored.transpose(2, 1, 0), lps)
    np.testing.assert_array_equal(expected, stored.transpose(1, 2, 0)[::-1, :, ::-1])  # the same, by hand
    with open_source(tmp_path / "sag", orient="LPS") as src:
        assert_like(src, expected.astype(np.uint16), affine)
        assert src.info.provenance["reoriented"] == {"source_axes": ["P", "I", "R"], "order": [2, 0, 1],
                                                     "flipped": [True, False, True]}
    store = lodcast.ingest(tmp_path / "sag", tmp_path / "sag.zarr")  # LPS by default
    assert store.orientation == ["L", "P", "S"] and store.summary()["orientation"] == ["L", "P", "S"]
    np.testing.assert_array_equal(store.level(0)[...], expected)
    np.testing.assert_allclose(store.origin, affine[:3, 3][::-1])  # no tilt: the origin is the patient position
    assert store.attrs["orientation"]["space"] == "LPS"
    np.testing.assert_allclose(store.summary()["direction"], np.eye(3), atol=1e-12)
    from lodcast.service.cli import main

    assert main(["ingest", str(tmp_path / "sag"), str(tmp_path / "again.zarr")]) == 0
    assert "the file's axes point P, I, R: turned to L, P, S (x, y, z)" in capsys.readouterr().out
    np.testing.assert_array_equal(lodcast.open_store(tmp_path / "again.zarr").level(0)[...], expected)
    assert main(["ingest", str(tmp_path / "sag"), str(tmp_path / "kept.zarr"), "--orient", "source"]) == 0
    assert "turned" not in capsys.readouterr().out
    kept = lodcast.open_store(tmp_path / "kept.zarr")
    assert kept.orientation == ["P", "I", "R"]
    np.testing.assert_array_equal(kept.level(0)[...], stored)  # slices in order along their normal, as read


def test_axis_codes_and_stores_written_before_reorientation(tmp_path):
    assert axis_codes("LPS", np.eye(3)) == ["L", "P", "S"]
    assert axis_codes("RAS", [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]) == ["L", "A", "S"]
    assert axis_codes("scanner-xyz", np.eye(3)) is None
    assert axis_codes("LPS", [[1, 0, 0], [1, 0, 0], [0, 0, 1]]) is None  # degenerate
    oblique = [[-0.99, 0.05, -0.10], [-0.02, -0.95, -0.31], [-0.11, -0.31, 0.95]]  # the FLAIR NRRD's
    assert legacy_axis_codes({"format": "nrrd", "space": "left-posterior-superior",
                              "space_directions": oblique}) == ["R", "A", "S"]
    assert legacy_axis_codes({"format": "dicom", "orientation": [0, 1, 0, 0, 0, -1]}) == ["P", "I", "R"]
    assert legacy_axis_codes({"format": "nifti", "affine": np.eye(4).tolist()}) == ["R", "A", "S"]
    assert legacy_axis_codes({"format": "npy"}) is None
    # a store of an older lodcast has no `orientation` attribute: its codes come from the provenance
    vol = np.random.default_rng(1).integers(0, 200, (6, 7, 8)).astype(np.uint8)
    nib.save(nib.Nifti1Image(vol.transpose(2, 1, 0), np.diag([-1.0, 1.0, 1.0, 1.0])), str(tmp_path / "mr.nii"))
    store = lodcast.ingest(tmp_path / "mr.nii", tmp_path / "mr.zarr", orient="source")
    assert store.orientation == ["L", "A", "S"] and store.attrs["orientation"]["space"] == "LPS"
    np.testing.assert_allclose(store.direction, np.diag([1.0, -1.0, 1.0]))
    import zarr

    g = zarr.open_group(tmp_path / "mr.zarr", mode="r+")  # as a format-3 store wrote it, before `orientation`
    g.attrs.pop("orientation")
    g.attrs["lodcast"] = {k: v for k, v in g.attrs["lodcast"].items() if k not in ("manifest", "integrity")} | {
        "format_version": 3}
    old = lodcast.open_store(tmp_path / "mr.zarr")
    assert old.orientation == ["L", "A", "S"] and old.direction is None
    with pytest.raises(SourceError, match="orient 'RAS': expected one of LPS, source"):
        open_source(tmp_path / "mr.nii", orient="RAS")
    nib.save(nib.Nifti1Image(vol.transpose(2, 1, 0), None), str(tmp_path / "uncoded.nii"))
    with open_source(tmp_path / "uncoded.nii") as src:  # no coded affine: no patient frame, nothing turned
        assert src.info.direction is None and src.info.origin == (0.0, 0.0, 0.0)
        np.testing.assert_array_equal(src.read(0, 6), vol)
        assert "this nifti source has no patient geometry" in src.info.provenance["orientation_kept"]
    nrrd.write(str(tmp_path / "scanner.nrrd"), vol[:, ::-1], {"space": "scanner-xyz",
                                                               "space directions": np.diag([1.0, -1.0, 1.0])})
    with open_source(tmp_path / "scanner.nrrd") as src:  # not a patient frame: kept, though y runs backwards
        assert src.info.provenance.get("reoriented") is None
        assert "'scanner-xyz' is not a patient frame" in src.info.provenance["orientation_kept"]
        np.testing.assert_array_equal(src.read(0, 8), vol[:, ::-1].transpose(2, 1, 0))


@pytest.mark.parametrize("codes, view, azimuth, elevation", [
    (["L", "P", "S"], "anterior", 0.0, 0.0), (["R", "A", "S"], "anterior", 180.0, 0.0),
    (["R", "A", "S"], "left", -90.0, 0.0), (["L", "P", "S"], "left", 90.0, 0.0),
    (["R", "A", "S"], "superior", 0.0, 90.0), (["L", "P", "I"], "superior", 0.0, -90.0)])
def test_named_views_put_the_eye_on_that_side(codes, view, azimuth, elevation):
    cam = resolve_view(OrbitCamera(view=view), codes)
    assert (cam.azimuth, cam.elevation, cam.view) == (pytest.approx(azimuth), pytest.approx(elevation), None)
    # the orbit eye direction (sin a cos e, -cos a cos e, sin e) is the named side's axis
    a, e = np.radians(cam.azimuth), np.radians(cam.elevation)
    np.testing.assert_allclose([np.sin(a) * np.cos(e), -np.cos(a) * np.cos(e), np.sin(e)],
                               view_direction(view, codes), atol=1e-12)


def test_a_dicom_ct_and_a_nifti_of_the_same_anatomy(tmp_path):
    """The same anatomy written as a DICOM series (LPS rows and columns) and as a NIfTI (RAS: x and y the other
    way). By default both are turned to one array, spacing and origin and show the face at azimuth 0
    (the eye at −y, anterior); with orient "source" the NIfTI keeps its file's axes (its level 0 is its array) and
    "anterior" resolves to azimuth 180. A named view renders as its azimuth does; a source without orientation is
    refused."""
    from test_readers import dicom_slice

    anatomy = np.random.default_rng(1).integers(0, 4096, (6, 16, 12)).astype(np.uint16)  # (S, P, L) indices
    (tmp_path / "ct").mkdir()
    for k in range(6):
        dicom_slice(tmp_path / "ct" / f"IM{k}", anatomy[k], 40.0 + 2.0 * k, intercept=0.0)
    ras = np.diag([0.25, 0.5, 2.0, 1.0])
    ras[:3, 3] = [10.0 - 11 * 0.25, 20.0 - 15 * 0.5, 40.0]  # voxel (0, 0, 0) is the right, anterior corner
    nib.save(nib.Nifti1Image(anatomy.transpose(2, 1, 0)[::-1, ::-1, :], ras), str(tmp_path / "mr.nii.gz"))
    kept = lodcast.ingest(tmp_path / "mr.nii.gz", tmp_path / "kept.zarr", orient="source")
    assert kept.orientation == ["R", "A", "S"]
    np.testing.assert_array_equal(kept.level(0)[...], anatomy[:, ::-1, ::-1])
    dicom = lodcast.ingest(tmp_path / "ct", tmp_path / "ct.zarr")
    nifti = lodcast.ingest(tmp_path / "mr.nii.gz", tmp_path / "mr.zarr")
    assert dicom.orientation == nifti.orientation == ["L", "P", "S"]
    np.testing.assert_array_equal(dicom.level(0)[...], anatomy)
    np.testing.assert_array_equal(nifti.level(0)[...], anatomy)
    assert dicom.spacing == nifti.spacing and dicom.origin == pytest.approx(nifti.origin)
    tf = {"points": [{"value": 0, "opacity": 0.0}, {"value": 4000, "opacity": 0.5}]}
    images = []
    for store, azimuth in ((dicom, 0.0), (nifti, 0.0), (kept, 180.0)):
        named = lodcast.render(store, {"tf": tf, "width": 24, "height": 24, "camera": {"view": "anterior"}})
        explicit = lodcast.render(store, {"tf": tf, "width": 24, "height": 24, "camera": {"azimuth": azimuth}})
        assert named.scene["camera"]["azimuth"] == pytest.approx(azimuth)
        np.testing.assert_array_equal(named.rgba, explicit.rgba)
        images.append(named.rgba)
    np.testing.assert_array_equal(images[0], images[1])
    np.testing.assert_allclose(images[2], images[0], atol=2e-5)  # the same face, seen from the same side
    with pytest.raises(SceneError, match="camera.view"):
        lodcast.render(np.zeros((4, 4, 4), np.float32), {"tf": tf, "camera": {"view": "left"}})
    with pytest.raises(SceneError, match="either a view or azimuth"):
        lodcast.Scene.parse({"tf": tf, "camera": {"view": "left", "azimuth": 10}})
