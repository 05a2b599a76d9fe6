"""Patient orientation (issue 15, item 7, in part): which patient direction each world axis points to, from
DICOM (LPS), NIfTI (RAS) and NRRD (its named space), and named views that put the eye on the same side of the
patient whatever the format: a DICOM CT at azimuth 0 shows the face, a NIfTI MR in RAS the back of the head;
`"view": "anterior"` shows both faces."""
from __future__ import annotations

import numpy as np
import pytest

import lodcast
from lodcast.renderer.camera import resolve_view
from lodcast.renderer.scene import OrbitCamera, SceneError
from lodcast.store.orientation import axis_codes, view_direction


def test_axis_codes_of_each_format():
    assert axis_codes({"format": "dicom", "orientation": [1, 0, 0, 0, 1, 0]}) == ["L", "P", "S"]
    assert axis_codes({"format": "dicom", "orientation": [-1, 0, 0, 0, 1, 0]}) == ["R", "P", "I"]  # normal flips
    assert axis_codes({"format": "dicom", "orientation": [0, 1, 0, 0, 0, -1]}) == ["P", "I", "R"]  # sagittal
    ras = np.diag([1.0, 1.0, 1.0, 1.0])
    assert axis_codes({"format": "nifti", "affine": ras.tolist()}) == ["R", "A", "S"]
    las = np.diag([-2.0, 2.0, 2.0, 1.0])
    assert axis_codes({"format": "nifti", "affine": las.tolist()}) == ["L", "A", "S"]
    oblique = [[-0.99, 0.05, -0.10], [-0.02, -0.95, -0.31], [-0.11, -0.31, 0.95]]  # the FLAIR NRRD's
    assert axis_codes({"format": "nrrd", "space": "left-posterior-superior", "space_directions": oblique}) == ["R", "A", "S"]
    assert axis_codes({"format": "nrrd", "space": "scanner-xyz", "space_directions": oblique}) is None
    assert axis_codes({"format": "nifti", "affine": np.diag([1.0, 1.0, 0.0, 1.0]).tolist()}) is None  # degenerate
    assert axis_codes({"format": "npy"}) is None


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


def test_the_same_view_of_a_dicom_and_a_nifti_volume(tmp_path):
    """The chest CT's geometry (DICOM, LPS) against an MR head's (NIfTI, RAS): "anterior" resolves to opposite
    azimuths, and renders exactly as the explicit azimuth does; a source without orientation is refused."""
    import nibabel as nib

    from test_readers import ct_series

    ct_series(tmp_path / "ct", 6)
    dicom = lodcast.ingest(tmp_path / "ct", tmp_path / "ct.zarr")
    vol = np.random.default_rng(1).integers(0, 200, (20, 24, 16)).astype(np.uint8)
    nib.save(nib.Nifti1Image(vol.transpose(2, 1, 0), np.diag([1.0, 1.0, 1.0, 1.0])), str(tmp_path / "mr.nii.gz"))
    nifti = lodcast.ingest(tmp_path / "mr.nii.gz", tmp_path / "mr.zarr")
    assert dicom.orientation == ["L", "P", "S"] and nifti.orientation == ["R", "A", "S"]
    assert dicom.summary()["orientation"] == ["L", "P", "S"]
    tf = {"points": [{"value": 0, "opacity": 0.0}, {"value": 3000, "opacity": 0.5}]}
    for store, azimuth in ((dicom, 0.0), (nifti, 180.0)):
        named = lodcast.render(store, {"tf": tf, "width": 24, "height": 24, "camera": {"view": "anterior"}})
        explicit = lodcast.render(store, {"tf": tf, "width": 24, "height": 24, "camera": {"azimuth": azimuth}})
        assert named.scene["camera"]["azimuth"] == pytest.approx(azimuth)
        np.testing.assert_array_equal(named.rgba, explicit.rgba)
    with pytest.raises(SceneError, match="camera.view"):
        lodcast.render(np.zeros((4, 4, 4), np.float32), {"tf": tf, "camera": {"view": "left"}})
    with pytest.raises(SceneError, match="either a view or azimuth"):
        lodcast.Scene.parse({"tf": tf, "camera": {"view": "left", "azimuth": 10}})
