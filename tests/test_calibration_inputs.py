"""Other people's RADLOCC-style recordings: JPEG images, camera.txt lines that name their images, intrinsics
from the Camera Calibration Toolbox for MATLAB (Calib_Results.mat), the view numbers that follow the input,
and a one-line error naming the file for each malformed input. Recordings are simulated (known truth) and
converted here."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from scipy.io import savemat

from dem_graph.calibration.readers import (
    CalibrationRecording,
    Intrinsics,
    read_bouguet_intrinsics,
    read_image_list,
    read_intrinsics_file,
    read_opencv_intrinsics,
    read_radlocc_recording,
    read_times,
)
from dem_graph.calibration.simulate import simulate_calibration, write_recording
from dem_graph.errors import DatasetError
from dem_graph.geometry.se3 import invert

SEED, N_VIEWS = 11, 8


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A simulated RADLOCC recording (PNGs, camera.txt, laser.txt, xml/, truth.yaml) and its simulation."""
    sim = simulate_calibration(seed=SEED, n_views=N_VIEWS)
    folder = write_recording(sim, tmp_path_factory.mktemp("sim") / "rec", seed=SEED, samples=1)
    return folder, sim


@pytest.fixture
def rec(simulated, tmp_path) -> Path:
    """A fresh copy of the simulated recording for one test to convert."""
    return Path(shutil.copytree(simulated[0], tmp_path / "rec"))


def _to_jpeg(png: Path, jpeg: Path) -> None:
    assert cv2.imwrite(str(jpeg), cv2.imread(str(png), cv2.IMREAD_UNCHANGED), [cv2.IMWRITE_JPEG_QUALITY, 95])
    png.unlink()


def _write_mat(path: Path, intr: Intrinsics, **override) -> None:
    """What the MATLAB toolbox saves, from ``intr``: its cc is OpenCV's (cx, cy) (both put (0,0) at the centre of
    the upper-left pixel); MATLAB stores vectors as columns and scalars as 1x1."""
    K = intr.K
    fields = {
        "fc": np.array([[K[0, 0]], [K[1, 1]]]),
        "cc": np.array([[K[0, 2]], [K[1, 2]]]),
        "alpha_c": np.array([[K[0, 1] / K[0, 0]]]),
        "kc": np.asarray(intr.distortion, dtype=float).reshape(5, 1),
        "nx": np.array([[float(intr.width_px)]]),
        "ny": np.array([[float(intr.height_px)]]),
        "KK": K,  # also in the toolbox's file; not read
    }
    fields.update(override)
    savemat(str(path), {k: v for k, v in fields.items() if v is not None})


def _names_recording(rec: Path, names: list[str], name_first: bool = False) -> np.ndarray:
    """Rename RGB<k>.png to JPEGs called ``names`` and write a camera.txt that lists them; the times."""
    data = rec / "data"
    times = read_times(data / "camera.txt")
    lines = []
    for k, (name, t) in enumerate(zip(names, times), start=1):
        (data / name).parent.mkdir(parents=True, exist_ok=True)
        _to_jpeg(data / f"RGB{k}.png", data / name)
        lines.append(f"{name} {float(t)!r}" if name_first else f"{float(t)!r} {name}")
    (data / "camera.txt").write_text("\n".join(lines) + "\n")
    return times


def _one_line_error(info, path: Path) -> None:
    message = str(info.value)
    assert str(path) in message and "\n" not in message, message


# ------------------------------------------------------------------ images: JPEG, names, numbers


def test_numbered_jpeg_images_read_like_the_pngs(simulated, rec):
    data = rec / "data"
    suffixes = [".jpg", ".JPG", ".jpeg", ".JPEG"]
    for k in range(1, N_VIEWS + 1):
        _to_jpeg(data / f"RGB{k}.png", data / f"RGB{k}{suffixes[k % 4]}")
    got = read_radlocc_recording(rec)
    assert got.image_names == [f"RGB{k}{suffixes[k % 4]}" for k in range(1, N_VIEWS + 1)]
    assert got.image_numbers == list(range(1, N_VIEWS + 1))
    np.testing.assert_array_equal(got.image_times_s, simulated[1].image_times_s)
    for k in range(N_VIEWS):
        png = cv2.imread(str(simulated[0] / "data" / f"RGB{k + 1}.png"), cv2.IMREAD_GRAYSCALE)
        jpeg = got.load_image(k)
        assert jpeg.shape == png.shape and jpeg.dtype == np.uint8
        assert np.mean(np.abs(jpeg.astype(float) - png.astype(float))) < 3.0
        assert got.load_image(k, color=True).shape == (*png.shape, 3)


def test_png_recording_is_read_as_before(simulated, rec):
    got = read_radlocc_recording(rec)
    assert got.image_names == [f"RGB{k}.png" for k in range(1, N_VIEWS + 1)]
    assert got.image_keys == [rec / "data" / f"RGB{k}.png" for k in range(1, N_VIEWS + 1)]
    assert got.view_numbers == list(range(1, N_VIEWS + 1))
    intr, board = read_opencv_intrinsics(rec / "xml" / "out_camera_data.xml")
    np.testing.assert_array_equal(got.intrinsics.K, intr.K)
    assert got.board == board == simulated[1].board


@pytest.mark.parametrize("name_first", [False, True])
def test_camera_txt_naming_its_images_in_either_order(simulated, rec, name_first):
    names = [f"cam/frame_{n:04d}.jpg" for n in (7, 9, 12, 20, 21, 30, 31, 40)]
    times = _names_recording(rec, names, name_first)
    listed_times, listed = read_image_list(rec / "data" / "camera.txt")
    assert listed == names
    np.testing.assert_array_equal(listed_times, times)
    got = read_radlocc_recording(rec)
    assert got.image_names == names
    assert got.image_keys == [rec / "data" / n for n in names]
    np.testing.assert_array_equal(got.image_times_s, simulated[1].image_times_s)
    assert got.image_numbers == got.view_numbers == [7, 9, 12, 20, 21, 30, 31, 40]
    png = cv2.imread(str(simulated[0] / "data" / "RGB3.png"), cv2.IMREAD_GRAYSCALE)
    assert np.mean(np.abs(got.load_image(2).astype(float) - png)) < 3.0


@pytest.mark.parametrize(
    "names",
    [
        ["left.jpg", "a.jpg", "b.jpg", "c.jpg", "d.jpg", "e.jpg", "f.jpg", "g.jpg"],  # no numbers
        ["a1.jpg", "b1.jpg", "c2.jpg", "d3.jpg", "e4.jpg", "f5.jpg", "g6.jpg", "h7.jpg"],  # 1 twice
    ],
)
def test_names_without_distinct_numbers_are_numbered_by_their_place(rec, names):
    _names_recording(rec, names)
    got = read_radlocc_recording(rec)
    assert got.image_names == names and got.image_numbers == list(range(1, N_VIEWS + 1))


def test_select_keeps_each_images_number(simulated, rec):
    _names_recording(rec, [f"img{n}.jpg" for n in range(101, 101 + N_VIEWS)])
    got = read_radlocc_recording(rec)
    picked = got.select([5, 2])
    assert picked.image_names == ["img106.jpg", "img103.jpg"] and picked.image_numbers == [106, 103]
    np.testing.assert_array_equal(picked.image_times_s, got.image_times_s[[5, 2]])
    unnumbered = CalibrationRecording(["a", "b", "c"], np.array([1.0, 2.0, 3.0]), got.scans, got.intrinsics, None, [0, 1, 2], lambda key, color: None)
    assert unnumbered.image_numbers is None and unnumbered.view_numbers == [1, 2, 3]
    assert unnumbered.select([2, 0]).view_numbers == [3, 1]


def test_time_only_camera_txt_lists_no_names(tmp_path):
    path = tmp_path / "camera.txt"
    path.write_text("1.5\n\n2.25 7.0\n3.0 4 5\n")  # numbers after the time: not names
    times, names = read_image_list(path)
    assert names is None
    np.testing.assert_array_equal(times, [1.5, 2.25, 3.0])
    np.testing.assert_array_equal(times, read_times(path))


@pytest.mark.parametrize(
    "text, message",
    [
        ("1.0 a.jpg\n2.0\n3.0 c.jpg\n", r"line 2: a time without an image name, but line 1 names its image"),
        ("1.0\n2.0 b.jpg\n", r"line 1: a time without an image name, but line 2 names its image"),
        ("1.0 a.jpg\nb.jpg\n", r"line 2: not TIME NAME or NAME TIME: 'b.jpg'"),
        ("1.0 a.jpg\n2.0 b c.jpg\n", r"line 2: not TIME NAME or NAME TIME: '2.0 b c.jpg'"),
        ("1.0 a.jpg\nnan b.jpg\n", r"line 2: not TIME NAME or NAME TIME"),
        ("2.0 a.jpg\n1.0 b.jpg\n", r"line 2: time 1.0 does not increase"),
        ("1.0 a.jpg\n2.0 a.jpg\n", r"line 2: image a.jpg is listed twice \(first on line 1\)"),
        ("1.0\nx\n", r"line 2: not a time stamp: 'x'"),  # a time-only file: read_times's messages
        ("2.0\n1.0\n", r"line 2: time 1.0 does not increase"),
        ("\n", r"no time stamps"),
    ],
)
def test_malformed_camera_txt_is_a_one_line_error_naming_file_and_line(tmp_path, text, message):
    path = tmp_path / "camera.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=message) as info:
        read_image_list(path)
    _one_line_error(info, path)


def test_listed_images_that_are_missing_are_counted(rec):
    names = [f"f{n}.jpg" for n in range(1, N_VIEWS + 1)]
    _names_recording(rec, names)
    for name in ("f3.jpg", "f5.jpg"):
        (rec / "data" / name).unlink()
    with pytest.raises(DatasetError, match=r"2 of 8 images listed in camera.txt are missing \(first: f3.jpg\)") as info:
        read_radlocc_recording(rec)
    _one_line_error(info, rec / "data")


def test_missing_numbered_image_is_counted(rec):
    (rec / "data" / "RGB4.png").unlink()
    with pytest.raises(DatasetError, match=r"1 of 8 images listed in camera.txt are missing \(first: RGB4.png/.jpg/.jpeg\)") as info:
        read_radlocc_recording(rec)
    _one_line_error(info, rec / "data")


def test_an_image_numbered_twice_is_an_error(rec):
    _to_jpeg(rec / "data" / "RGB2.png", rec / "data" / "RGB2.jpg")
    shutil.copy(rec / "data" / "RGB1.png", rec / "data" / "RGB2.png")
    with pytest.raises(DatasetError, match=r"image 2 is both RGB2.jpg and RGB2.png: keep one") as info:
        read_radlocc_recording(rec)
    _one_line_error(info, rec / "data")


# ------------------------------------------------------------------ MATLAB intrinsics


def test_calib_results_mat_round_trip(tmp_path):
    K = np.array([[812.25, 812.25 * 0.0015, 331.125], [0.0, 809.5, 247.875], [0.0, 0.0, 1.0]])
    intr = Intrinsics(K, np.array([-0.21, 0.13, 0.0011, -0.0007, -0.02]), 752, 480)
    _write_mat(tmp_path / "Calib_Results.mat", intr)
    got, board = read_bouguet_intrinsics(tmp_path / "Calib_Results.mat")
    assert board is None
    np.testing.assert_allclose(got.K, K, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.distortion, intr.distortion, rtol=0, atol=1e-12)
    assert (got.width_px, got.height_px) == (752, 480)
    again, _ = read_intrinsics_file(tmp_path / "Calib_Results.mat")
    np.testing.assert_array_equal(again.K, got.K)


def test_calib_results_cc_is_opencvs_principal_point(tmp_path):
    """The toolbox starts cc at [nx;ny]/2 - 0.5, the image's centre with (0,0) at the centre of the upper-left
    pixel: OpenCV's centre ((w-1)/2, (h-1)/2), so no offset."""
    nx, ny = 640, 480
    intr = Intrinsics(np.array([[500.0, 0.0, nx / 2 - 0.5], [0.0, 500.0, ny / 2 - 0.5], [0.0, 0.0, 1.0]]), np.zeros(5), nx, ny)
    _write_mat(tmp_path / "Calib_Results.mat", intr)
    got, _ = read_bouguet_intrinsics(tmp_path / "Calib_Results.mat")
    assert got.K[0, 2] == (nx - 1) / 2 and got.K[1, 2] == (ny - 1) / 2


def test_old_toolbox_four_distortion_coefficients(tmp_path):
    intr = Intrinsics(np.array([[500.0, 0.0, 300.0], [0.0, 500.0, 200.0], [0.0, 0.0, 1.0]]), np.zeros(5), 600, 400)
    _write_mat(tmp_path / "Calib_Results.mat", intr, kc=np.array([[-0.2], [0.1], [0.001], [0.002]]))
    got, _ = read_bouguet_intrinsics(tmp_path / "Calib_Results.mat")
    np.testing.assert_array_equal(got.distortion, [-0.2, 0.1, 0.001, 0.002, 0.0])


@pytest.mark.parametrize(
    "override, message",
    [
        ({"kc": None}, r"field kc missing"),
        ({"nx": None}, r"field nx missing"),
        ({"fc": np.array([[500.0], [500.0], [1.0]])}, r"field fc has 3 values, expected 2"),
        ({"cc": np.array([[300.0]])}, r"field cc has 1 values, expected 2"),
        ({"kc": np.zeros((3, 1))}, r"field kc has 3 values, expected 5 or 4"),
        ({"alpha_c": np.array([[0.0, 0.0]])}, r"field alpha_c has 2 values, expected 1"),
        ({"cc": np.array([[np.nan], [200.0]])}, r"field cc is not finite"),
        ({"kc": np.array([[0.1], [np.inf], [0.0], [0.0], [0.0]])}, r"field kc is not finite"),
        ({"fc": np.array([[500.0], [-500.0]])}, r"field fc must be positive"),
        ({"ny": np.array([[0.0]])}, r"field ny must be a whole number of pixels, at least 1"),
        ({"nx": np.array([[640.5]])}, r"field nx must be a whole number of pixels"),
        ({"fc": "five hundred"}, r"field fc is not a real number array"),
    ],
)
def test_malformed_calib_results_is_a_one_line_error_naming_the_field(tmp_path, override, message):
    intr = Intrinsics(np.array([[500.0, 0.0, 300.0], [0.0, 500.0, 200.0], [0.0, 0.0, 1.0]]), np.zeros(5), 600, 400)
    path = tmp_path / "Calib_Results.mat"
    _write_mat(path, intr, **override)
    with pytest.raises(DatasetError, match=message) as info:
        read_bouguet_intrinsics(path)
    _one_line_error(info, path)


@pytest.mark.parametrize(
    "content, message",
    [
        (None, r"intrinsics file not found"),
        (b"", r"not a MATLAB MAT file"),
        (b"fc = [500; 500]\n" * 20, r"not a MATLAB MAT file"),
    ],
)
def test_unreadable_calib_results_is_a_one_line_error(tmp_path, content, message):
    path = tmp_path / "Calib_Results.mat"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(DatasetError, match=message) as info:
        read_bouguet_intrinsics(path)
    _one_line_error(info, path)


def test_where_the_recording_finds_its_intrinsics(simulated, rec):
    sim = simulated[1]
    other = Intrinsics(sim.intrinsics.K * np.array([[1.1], [1.1], [1.0]]), np.zeros(5), 640, 480)
    _write_mat(rec / "Calib_Results.mat", other)
    _write_mat(rec / "data" / "Calib_Results.mat", sim.intrinsics)
    first = read_radlocc_recording(rec)  # xml/out_camera_data.xml first: it also gives the board
    np.testing.assert_allclose(first.intrinsics.K, sim.intrinsics.K, atol=1e-9)
    assert first.board == sim.board
    shutil.rmtree(rec / "xml")
    second = read_radlocc_recording(rec)  # then Calib_Results.mat beside data/
    np.testing.assert_allclose(second.intrinsics.K, other.K, rtol=0, atol=1e-12)
    assert second.board is None
    (rec / "Calib_Results.mat").unlink()
    third = read_radlocc_recording(rec)  # then in data/
    np.testing.assert_allclose(third.intrinsics.K, sim.intrinsics.K, rtol=0, atol=1e-12)
    np.testing.assert_allclose(third.intrinsics.distortion, sim.intrinsics.distortion, rtol=0, atol=1e-12)
    (rec / "data" / "Calib_Results.mat").unlink()
    with pytest.raises(DatasetError, match=r"no intrinsics file: neither xml/out_camera_data.xml .* nor Calib_Results.mat .*here or in data/") as info:
        read_radlocc_recording(rec)
    _one_line_error(info, rec)


def test_intrinsics_given_explicitly_override_the_folders(simulated, rec, tmp_path):
    sim = simulated[1]
    other = Intrinsics(sim.intrinsics.K * np.array([[0.9], [0.9], [1.0]]), np.array([0.01, 0.0, 0.0, 0.0, 0.0]), 640, 480)
    mat = tmp_path / "elsewhere" / "calib.MAT"
    mat.parent.mkdir()
    _write_mat(mat, other)
    got = read_radlocc_recording(rec, intrinsics_path=mat)
    np.testing.assert_allclose(got.intrinsics.K, other.K, rtol=0, atol=1e-12)
    assert got.board is None
    xml = rec / "xml" / "out_camera_data.xml"
    shutil.move(xml, tmp_path / "cam.yml.xml")
    from_xml = read_radlocc_recording(rec, intrinsics_path=tmp_path / "cam.yml.xml")
    assert from_xml.board == sim.board
    with pytest.raises(DatasetError, match="intrinsics file not found") as info:
        read_radlocc_recording(rec, intrinsics_path=tmp_path / "none.mat")
    _one_line_error(info, tmp_path / "none.mat")


# ------------------------------------------------------------------ through the command


def test_calibrate_command_on_jpeg_names_and_mat(simulated, rec, tmp_path):
    from dem_graph.cli import main

    sim = simulated[1]
    names = [f"shot-{n}.jpeg" for n in range(50, 50 + N_VIEWS)]
    _names_recording(rec, names)
    _write_mat(rec / "Calib_Results.mat", sim.intrinsics)
    shutil.rmtree(rec / "xml")
    truth = yaml.safe_load((rec / "truth.yaml").read_text())
    board = truth["board"]
    out = tmp_path / "out"
    args = ["calibrate", str(rec), "--intrinsics", str(rec / "Calib_Results.mat"), "--out", str(out), "--camera-height-m", "1.2", "--camera-pitch-deg", "20"]
    args += ["--board", f"{board['cols']}x{board['rows']}", "--square-m", str(board["square_m"])]  # a .mat file has no board
    run = CliRunner().invoke(main, args)
    assert run.exit_code == 0, run.output
    assert "T_cam_laser from" in run.output
    T = np.asarray(json.loads((out / "calibration.json").read_text())["T_cam_laser"])
    T_true = np.asarray(truth["T_cam_laser"])
    delta = invert(T_true) @ T
    angle_deg = np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1, 1)))
    assert angle_deg < 1.0 and np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.020, (angle_deg, T[:3, 3] - T_true[:3, 3])


def test_command_keeps_refusing_topic_options_for_radlocc(simulated, rec, tmp_path):
    from dem_graph.cli import main

    run = CliRunner().invoke(main, ["calibrate", str(rec), "--scan-topic", "/scan", "--out", str(tmp_path / "o")])
    assert run.exit_code == 2 and "--scan-topic: only for --format rosbag" in run.output


def test_command_reads_a_mat_file_only_for_radlocc(tmp_path):
    from dem_graph.cli import main

    args = ["calibrate", str(tmp_path / "cal.bag"), "--format", "rosbag", "--image-topic", "/image", "--scan-topic", "/scan"]
    run = CliRunner().invoke(main, [*args, "--intrinsics", str(tmp_path / "Calib_Results.mat"), "--out", str(tmp_path / "o")])
    assert run.exit_code == 2 and "--intrinsics: a MATLAB .mat file is read only with --format radlocc" in run.output
