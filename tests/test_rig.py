"""Truth-checked tests of dem_graph.geometry.rig: the default rig's geometry, YAML round trip, validation."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml

from dem_graph.errors import ConfigError
from dem_graph.geometry.rig import (
    CameraSpec,
    DirectionBeams,
    OdometrySpec,
    PlanarBeams,
    default_rig,
    load_rig,
    rig_from_dict,
    rig_to_dict,
    save_rig,
    validated,
)
from dem_graph.geometry.se3 import make_pose, rotation_from_rpy

# ------------------------------------------------------------------ default geometry


def test_default_laser_beam_zero_hits_ground_3m_ahead():
    rig = default_rig()
    T = rig.T_body_laser
    p = T[:3, 3]
    angles = rig.laser.beams.angle_min_rad + rig.laser.beams.angle_increment_rad * np.arange(rig.laser.beams.count)
    k0 = int(np.argmin(np.abs(angles)))
    assert abs(angles[k0]) < 1e-12  # there is a beam at angle 0
    d_laser = rig.laser.beam_directions()[k0]
    np.testing.assert_allclose(d_laser, [1.0, 0.0, 0.0], atol=1e-12)
    d = T[:3, :3] @ d_laser
    assert d[2] < 0  # pointing down
    s = -p[2] / d[2]  # ray p + s d meets z = 0
    hit = p + s * d
    assert hit[2] == pytest.approx(0.0, abs=1e-12)
    assert np.linalg.norm(hit[:2] - p[:2]) == pytest.approx(3.0, abs=0.01)
    assert hit[0] > p[0]  # ahead of the mount
    assert hit[1] == pytest.approx(0.0, abs=1e-12)
    # the whole scan is in a plane through the laser containing the body y axis
    n = T[:3, :3] @ [0.0, 0.0, 1.0]
    dirs_body = rig.laser.beam_directions() @ T[:3, :3].T
    np.testing.assert_allclose(dirs_body @ n, 0.0, atol=1e-12)


def test_default_camera_looks_forward_and_20_degrees_down():
    R = default_rig().T_body_cam[:3, :3]
    a = np.radians(20.0)
    np.testing.assert_allclose(R @ [0.0, 0.0, 1.0], [np.cos(a), 0.0, -np.sin(a)], rtol=0, atol=1e-9)  # optical axis
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], rtol=0, atol=1e-9)  # image right = body right
    np.testing.assert_allclose(R @ [0.0, 1.0, 0.0], [-np.sin(a), 0.0, -np.cos(a)], rtol=0, atol=1e-9)  # image down
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


def test_T_cam_laser():
    rig = default_rig()
    T_body_cam, T_body_laser = rig.T_body_cam, rig.T_body_laser
    np.testing.assert_allclose(rig.T_cam_laser, np.linalg.inv(T_body_cam) @ T_body_laser, rtol=0, atol=1e-12)
    # the laser origin lands at the laser position expressed in the camera frame
    p_laser_cam = T_body_cam[:3, :3].T @ (T_body_laser[:3, 3] - T_body_cam[:3, 3])
    np.testing.assert_allclose((rig.T_cam_laser @ [0.0, 0.0, 0.0, 1.0])[:3], p_laser_cam, atol=1e-12)
    # the default laser is 10 cm ahead of and 40 cm below the camera: in OpenCV axes that is
    # y down > 0; and it is in the camera's x = 0 plane
    assert p_laser_cam[0] == pytest.approx(0.0, abs=1e-12)
    assert p_laser_cam[1] > 0
    np.testing.assert_allclose(np.linalg.norm(p_laser_cam), np.hypot(0.1, 0.4), atol=1e-12)
    # the 3 m ground hit projects into the image (below the centre)
    d = T_body_laser[:3, :3] @ [1.0, 0.0, 0.0]
    hit_body = T_body_laser[:3, 3] + (-T_body_laser[2, 3] / d[2]) * d
    hit_cam = (np.linalg.inv(T_body_cam) @ np.append(hit_body, 1.0))[:3]
    uv, in_front = rig.camera_model.project(hit_cam[None])
    assert in_front[0] and rig.camera_model.in_image(uv)[0]
    assert uv[0, 0] == pytest.approx(rig.camera.cx_px, abs=1e-9)
    assert uv[0, 1] > rig.camera.cy_px


# ------------------------------------------------------------------------- YAML


def _assert_rigs_equal(a, b):
    assert np.array_equal(a.T_body_cam, b.T_body_cam)
    assert np.array_equal(a.T_body_laser, b.T_body_laser)
    assert np.array_equal(a.T_cam_laser, b.T_cam_laser)
    ca, cb = a.camera, b.camera
    for name in ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "rate_hz", "noise_sigma_dn"):
        assert getattr(ca, name) == getattr(cb, name), name
    assert tuple(ca.distortion) == tuple(cb.distortion)
    assert a.camera_model == b.camera_model
    assert type(a.laser.beams) is type(b.laser.beams)
    assert a.laser.beams == b.laser.beams
    assert np.array_equal(a.laser.beam_directions(), b.laser.beam_directions())
    for name in ("range_min_m", "range_max_m", "range_sigma_m", "rate_hz"):
        assert getattr(a.laser, name) == getattr(b.laser, name), name
    assert a.odometry == b.odometry
    assert a.T_cam_laser_covariance == b.T_cam_laser_covariance


def test_default_rig_yaml_round_trip(tmp_path):
    rig = default_rig()
    path = tmp_path / "rig.yaml"
    save_rig(rig, path)
    back = load_rig(path)
    _assert_rigs_equal(rig, back)
    assert isinstance(back.laser.beams, PlanarBeams)
    assert back.T_body_cam.dtype == float and back.T_body_cam.shape == (4, 4)
    # saving the loaded rig writes the identical file
    path2 = tmp_path / "rig2.yaml"
    save_rig(back, path2)
    assert path2.read_text() == path.read_text()


def test_direction_beams_rig_round_trip(tmp_path):
    rng = np.random.default_rng(21)
    d = rng.normal(size=(16, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    data = rig_to_dict(default_rig())
    data["laser"]["beams"] = {"kind": "directions", "directions_xyz": d.tolist()}
    cov = np.diag([1e-6, 2e-6, 3e-6, 1e-4, 2e-4, 3e-4]) + 1e-8
    data["T_cam_laser_covariance"] = cov.tolist()
    data["odometry"] = None
    rig = rig_from_dict(data)
    assert isinstance(rig.laser.beams, DirectionBeams)
    assert rig.laser.beams.count == 16
    np.testing.assert_array_equal(rig.laser.beam_directions(), d)
    path = tmp_path / "rig.yaml"
    save_rig(rig, path)
    back = load_rig(path)
    _assert_rigs_equal(rig, back)
    assert back.odometry is None
    np.testing.assert_array_equal(np.asarray(back.T_cam_laser_covariance), cov)
    np.testing.assert_array_equal(back.laser.beam_directions(), d)


# -------------------------------------------------------------------- validation


def _write(tmp_path, data, name="rig.yaml"):
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return path


def _assert_config_error(path, *fragments):
    with pytest.raises(ConfigError) as info:
        load_rig(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    assert info.value.source == str(path)
    for f in fragments:
        assert f in msg, f"{f!r} not in {msg!r}"
    return msg


def test_missing_file(tmp_path):
    _assert_config_error(tmp_path / "nope" / "rig.yaml", "not found")


def test_directory_instead_of_file(tmp_path):
    _assert_config_error(tmp_path, "not found")


def test_invalid_yaml(tmp_path):
    path = _write(tmp_path, "camera: [1, 2\nlaser: {\n")
    _assert_config_error(path, "YAML")


@pytest.mark.parametrize("text", ["- camera\n- laser\n", "just a string\n", "", "42\n"])
def test_top_level_not_a_mapping(tmp_path, text):
    _assert_config_error(_write(tmp_path, text), "mapping")


def _modified(mod):
    data = copy.deepcopy(rig_to_dict(default_rig()))
    mod(data)
    return data


def _set_nan(data):
    data["laser"]["T_body_laser"][1][3] = float("nan")


def _non_unit_beams(data):
    data["laser"]["beams"] = {"kind": "directions", "directions_xyz": [[1.0, 0.0, 0.0], [0.6, 0.6, 0.0]]}


CASES = {
    "cam_3x3": (lambda d: d["camera"].__setitem__("T_body_cam", np.eye(3).tolist()), ["camera.T_body_cam", "4x4"]),
    "cam_3x4": (lambda d: d["camera"].__setitem__("T_body_cam", d["camera"]["T_body_cam"][:3]), ["camera.T_body_cam", "4x4"]),
    "laser_nan": (_set_nan, ["laser.T_body_laser", "NaN"]),
    "laser_not_rotation": (
        lambda d: d["laser"]["T_body_laser"][0].__setitem__(0, 2.0),
        ["laser.T_body_laser", "rotation"],
    ),
    "non_unit_beam": (_non_unit_beams, ["directions_xyz", "unit"]),
    "range_equal": (lambda d: d["laser"].update(range_min_m=5.0, range_max_m=5.0), ["range_max_m"]),
    "range_inverted": (lambda d: d["laser"].update(range_min_m=5.0, range_max_m=1.0), ["range_max_m"]),
    "negative_fx": (lambda d: d["camera"].__setitem__("fx_px", -560.0), ["camera.fx_px"]),
    "zero_fy": (lambda d: d["camera"].__setitem__("fy_px", 0.0), ["camera.fy_px"]),
    "typo_camera": (lambda d: d["camera"].__setitem__("fx_pxx", 560.0), ["camera.fx_pxx"]),
    "typo_top": (lambda d: d.__setitem__("lasr", {}), ["lasr"]),
    "typo_odometry": (lambda d: d["odometry"].__setitem__("sigma_scael", 0.1), ["odometry.sigma_scael"]),
    "cov_5x5": (lambda d: d.__setitem__("T_cam_laser_covariance", np.eye(5).tolist()), ["T_cam_laser_covariance", "6x6"]),
    "cov_6x5": (lambda d: d.__setitem__("T_cam_laser_covariance", np.eye(6)[:, :5].tolist()), ["T_cam_laser_covariance"]),
    "cov_asym": (
        lambda d: d.__setitem__("T_cam_laser_covariance", (np.eye(6) + np.triu(np.ones((6, 6)), 1)).tolist()),
        ["T_cam_laser_covariance", "symmetric"],
    ),
    "missing_camera_pose": (lambda d: d["camera"].pop("T_body_cam"), ["camera.T_body_cam"]),
    "missing_laser": (lambda d: d.pop("laser"), ["laser"]),
    # every value a run uses: finite, in its range, with the field named and what it must be
    "nan_cx": (
        lambda d: d["camera"].__setitem__("cx_px", float("nan")),
        ["camera.cx_px is nan; it must be a finite pixel coordinate inside the image (-0.5 to 799.5)"],
    ),
    "cx_outside": (
        lambda d: d["camera"].__setitem__("cx_px", 800.0),
        ["camera.cx_px is 800.0; it must be a finite pixel coordinate inside the image"],
    ),
    "cy_negative": (
        lambda d: d["camera"].__setitem__("cy_px", -3.0),
        ["camera.cy_px is -3.0; it must be a finite pixel coordinate inside the image (-0.5 to 599.5)"],
    ),
    "nan_fx": (lambda d: d["camera"].__setitem__("fx_px", float("nan")), ["camera.fx_px is nan; it must be a finite number above 0"]),
    "inf_fy": (lambda d: d["camera"].__setitem__("fy_px", float("inf")), ["camera.fy_px is inf; it must be a finite number above 0"]),
    "nan_distortion": (
        lambda d: d["camera"]["distortion"].__setitem__(1, float("nan")),
        ["camera.distortion has k2 = nan; every coefficient must be a finite number"],
    ),
    "inf_camera_rate": (
        lambda d: d["camera"].__setitem__("rate_hz", float("inf")),
        ["camera.rate_hz is inf; it must be a finite number above 0"],
    ),
    "negative_image_noise": (
        lambda d: d["camera"].__setitem__("noise_sigma_dn", -1.0),
        ["camera.noise_sigma_dn is -1.0; it must be a finite number, 0 or more"],
    ),
    "cam_not_rigid": (
        lambda d: d["camera"]["T_body_cam"][0].__setitem__(0, 1.5),
        ["camera.T_body_cam rotation block is not a proper rotation"],
    ),
    "cam_inf": (lambda d: d["camera"]["T_body_cam"][2].__setitem__(3, float("inf")), ["camera.T_body_cam contains NaN or infinite values"]),
    "laser_rate_zero": (lambda d: d["laser"].__setitem__("rate_hz", 0.0), ["laser.rate_hz is 0.0; it must be a finite number above 0"]),
    "range_min_nan": (
        lambda d: d["laser"].__setitem__("range_min_m", float("nan")),
        ["laser.range_min_m is nan; it must be a finite number, 0 or more"],
    ),
    "range_max_inf": (
        lambda d: d["laser"].__setitem__("range_max_m", float("inf")),
        ["laser.range_max_m is inf; it must be a finite number above 0"],
    ),
    "range_sigma_negative": (
        lambda d: d["laser"].__setitem__("range_sigma_m", -0.01),
        ["laser.range_sigma_m is -0.01; it must be a finite number, 0 or more"],
    ),
    "beam_angle_nan": (
        lambda d: d["laser"]["beams"].__setitem__("angle_min_rad", float("nan")),
        ["laser.beams.angle_min_rad is nan; it must be a finite number"],
    ),
    "beam_step_zero": (
        lambda d: d["laser"]["beams"].__setitem__("angle_increment_rad", 0.0),
        ["laser.beams.angle_increment_rad is 0.0; it must be a finite number above 0"],
    ),
    "beams_over_a_turn": (
        lambda d: d["laser"]["beams"].__setitem__("count", 1000),
        ["laser.beams.count is 1000; 1000 beams every", "span more than a full turn"],
    ),
    "odometry_rate_nan": (
        lambda d: d["odometry"].__setitem__("rate_hz", float("nan")),
        ["odometry.rate_hz is nan; it must be a finite number above 0"],
    ),
    "odometry_sigma_negative": (
        lambda d: d["odometry"].__setitem__("sigma_yaw_rad_per_sqrt_m", -0.1),
        ["odometry.sigma_yaw_rad_per_sqrt_m is -0.1; it must be a finite number, 0 or more"],
    ),
    "odometry_floor_zero": (
        lambda d: d["odometry"].__setitem__("min_distance_m", 0.0),
        ["odometry.min_distance_m is 0.0; it must be a finite number above 0"],
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_invalid_rig_values(tmp_path, case):
    mod, fragments = CASES[case]
    path = _write(tmp_path, _modified(mod))
    msg = _assert_config_error(path, *fragments)
    assert msg.startswith(f"{path}: ") and "\n" not in msg


def test_a_full_turn_of_beams_is_allowed():
    beams = PlanarBeams(angle_min_rad=-np.pi, angle_increment_rad=2 * np.pi / 360, count=361)
    assert beams.count == 361


def test_a_principal_point_on_the_image_border_is_allowed():
    data = _modified(lambda d: d["camera"].update(cx_px=-0.5, cy_px=599.5))
    rig = rig_from_dict(data)
    assert (rig.camera.cx_px, rig.camera.cy_px) == (-0.5, 599.5)


def test_validated_names_the_source_and_the_field_under_a_prefix():
    data = rig_to_dict(default_rig())["camera"]
    data["fx_px"] = -1.0
    with pytest.raises(ConfigError) as info:
        validated(CameraSpec, data, "calib.txt", "camera")
    assert str(info.value) == "calib.txt: camera.fx_px is -1.0; it must be a finite number above 0"


def test_rig_from_dict_without_source_still_names_the_field():
    with pytest.raises(ConfigError) as info:
        rig_from_dict(_modified(lambda d: d["camera"].__setitem__("fx_px", -1.0)))
    assert info.value.source is None
    assert str(info.value) == "camera.fx_px is -1.0; it must be a finite number above 0"


def test_assignment_is_validated_too():
    camera = default_rig().camera
    with pytest.raises(ValueError, match="cx_px"):
        camera.cx_px = float("nan")


# --------------------------------------------------------------------- odometry


def test_increment_covariance_hand_computed():
    spec = OdometrySpec(
        sigma_scale=0.02,
        sigma_forward_m_per_sqrt_m=0.01,
        sigma_lateral_m_per_sqrt_m=0.03,
        sigma_vertical_m_per_sqrt_m=0.05,
        sigma_yaw_rad_per_sqrt_m=0.002,
        sigma_roll_pitch_rad_per_sqrt_m=0.004,
        min_distance_m=0.05,
    )
    d = 4.0
    C = spec.increment_covariance(d)
    assert C.shape == (6, 6)
    # [roll, pitch, yaw, forward, lateral, vertical]
    expected = [
        0.004**2 * 4.0,  # 6.4e-5
        0.004**2 * 4.0,
        0.002**2 * 4.0,  # 1.6e-5
        0.01**2 * 4.0 + (0.02 * 4.0) ** 2,  # 4e-4 + 6.4e-3 = 6.8e-3
        0.03**2 * 4.0,  # 3.6e-3
        0.05**2 * 4.0,  # 1.0e-2
    ]
    np.testing.assert_allclose(np.diag(C), [6.4e-5, 6.4e-5, 1.6e-5, 6.8e-3, 3.6e-3, 1.0e-2], rtol=1e-12)
    np.testing.assert_allclose(np.diag(C), expected, rtol=1e-12)
    np.testing.assert_array_equal(C - np.diag(np.diag(C)), 0.0)


def test_increment_covariance_default_spec():
    C = OdometrySpec().increment_covariance(1.0)
    one_deg, half_deg = np.radians(1.0), np.radians(0.5)
    np.testing.assert_allclose(
        np.diag(C), [one_deg**2, one_deg**2, half_deg**2, 1e-4 + 1e-4, 1e-4, 4e-4], rtol=1e-12
    )


def test_increment_covariance_distance_floor():
    spec = OdometrySpec(min_distance_m=0.05)
    at_floor = spec.increment_covariance(0.05)
    for d in (0.0, 1e-6, 0.03, -1.0):
        np.testing.assert_array_equal(spec.increment_covariance(d), at_floor)
    np.testing.assert_allclose(at_floor[5, 5], 0.02**2 * 0.05, rtol=1e-12)
    # above the floor the covariance grows
    assert np.all(np.diag(spec.increment_covariance(0.1)) > np.diag(at_floor))
    # all diagonal entries strictly positive at the floor, so the noise model is never singular
    assert np.all(np.diag(at_floor) > 0)


def test_covariance_of_an_increment_is_the_model_for_its_length():
    spec = OdometrySpec()
    T = make_pose(rotation_from_rpy(0.01, -0.02, 0.3), [0.3, 0.4, 0.0])  # 0.5 m
    np.testing.assert_array_equal(spec.covariance_of(T), spec.increment_covariance(0.5))
