"""Recording files: HDF5 and CSV read into the same arrays, the documented layout, atomic writes, one-line errors."""

import h5py
import numpy as np
import pytest

import jaxspring as js

NAN = np.nan


def _write_h5(path, attrs=None, **datasets):
    """A hand-made HDF5 file: root attributes and datasets exactly as given."""
    with h5py.File(path, "w") as f:
        f.attrs.update({"format": "jaxspring.recording", "format_version": 1} if attrs is None else attrs)
        for name, data in datasets.items():
            f.create_dataset(name, data=data)
    return path


def _two_markers():
    """3 frames, 2 markers; marker 1 lost at frame 1."""
    t = np.array([0.0, 0.01, 0.02])
    x = np.array(
        [
            [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]],
            [[0.1, 1.1, 2.1], [NAN, NAN, NAN]],
            [[0.2, 1.2, 2.2], [3.2, 4.2, 5.2]],
        ]
    )
    return t, x


def test_hdf5_round_trip_and_layout(tmp_path):
    t, x = _two_markers()
    rec = js.Recording(t=t, x=x, markers=("left", "right"))
    path = tmp_path / "take.h5"
    js.save_recording(path, rec)
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "jaxspring.recording" and int(f.attrs["format_version"]) == 1
        assert f["t"].dtype == np.float64 and f["t"].shape == (3,)
        assert f["x"].dtype == np.float64 and f["x"].shape == (3, 2, 3)
        assert [name for name in f["markers"].asstr()[()]] == ["left", "right"]
        np.testing.assert_array_equal(f["x"][()], x)  # NaN stored where not seen
    loaded = js.load_recording(path)
    np.testing.assert_array_equal(loaded.t, t)
    np.testing.assert_array_equal(loaded.x, x)
    assert loaded.markers == ("left", "right")
    assert loaded.t.dtype == np.float64 and loaded.x.dtype == np.float64
    assert loaded.frame_count == 3 and loaded.marker_count == 2
    np.testing.assert_array_equal(loaded.seen, [[True, True], [True, False], [True, True]])


def test_default_names_and_arrays_are_private_copies(tmp_path):
    t, x = _two_markers()
    rec = js.Recording(t=t, x=x)
    assert rec.markers == ("m0", "m1")
    x[0, 0, 0] = 99.0  # the caller's array is not shared
    assert rec.x[0, 0, 0] == 0.0
    with pytest.raises(ValueError):
        rec.x[0, 0, 0] = 1.0  # read-only
    # a file without /markers gets the default names too
    path = _write_h5(tmp_path / "plain.h5", t=t, x=x)
    assert js.load_recording(path).markers == ("m0", "m1")


def test_csv_with_empty_cells(tmp_path):
    path = tmp_path / "take.csv"
    path.write_text(
        "t,tip_x,tip_y,tip_z,base_x,base_y,base_z\n0.00,1,2,3,4,5,6\n0.01,1.5,2.5,3.5,,,\n0.02, -1e-3 ,0,0.25,4,5,6.5\n"
    )
    rec = js.load_recording(path)
    assert rec.markers == ("tip", "base")
    np.testing.assert_array_equal(rec.t, [0.0, 0.01, 0.02])
    expected = np.array(
        [
            [[1, 2, 3], [4, 5, 6]],
            [[1.5, 2.5, 3.5], [NAN, NAN, NAN]],
            [[-0.001, 0, 0.25], [4, 5, 6.5]],
        ]
    )
    np.testing.assert_array_equal(rec.x, expected)
    assert rec.x.dtype == np.float64
    np.testing.assert_array_equal(rec.seen, [[True, True], [True, False], [True, True]])
    # the same content under another name is recognised by its header
    other = tmp_path / "take.txt"
    other.write_bytes(path.read_bytes())
    np.testing.assert_array_equal(js.load_recording(other).x, expected)
    # and a CSV round-trips through the HDF5 file
    js.save_recording(tmp_path / "take.h5", rec)
    np.testing.assert_array_equal(js.load_recording(tmp_path / "take.h5").x, expected)


@pytest.mark.parametrize("dtype", [np.float32, np.int32, np.int64])
def test_hdf5_numbers_are_cast_to_float64(tmp_path, dtype):
    t = np.array([0, 1, 2], dtype=dtype)
    x = np.arange(3 * 2 * 3).reshape(3, 2, 3).astype(dtype)
    rec = js.load_recording(_write_h5(tmp_path / "typed.h5", t=t, x=x))
    assert rec.t.dtype == np.float64 and rec.x.dtype == np.float64
    np.testing.assert_array_equal(rec.t, [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(rec.x, np.arange(18.0).reshape(3, 2, 3))


def test_atomic_write_leaves_no_temporary_file(tmp_path):
    t, x = _two_markers()
    path = tmp_path / "take.h5"
    js.save_recording(path, js.Recording(t=t, x=x))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["take.h5"]
    # a write that fails half way keeps the old file and leaves nothing else behind
    broken = js.Recording(t=t + 1.0, x=x)
    object.__setattr__(broken, "markers", (object(), object()))  # not storable as strings
    with pytest.raises((TypeError, ValueError)):
        js.save_recording(path, broken)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["take.h5"]
    np.testing.assert_array_equal(js.load_recording(path).t, t)


def test_save_refuses_a_missing_folder_and_a_csv_name(tmp_path):
    t, x = _two_markers()
    with pytest.raises(js.InputError, match="does not exist"):
        js.save_recording(tmp_path / "nowhere" / "take.h5", js.Recording(t=t, x=x))
    with pytest.raises(js.InputError, match="HDF5"):
        js.save_recording(tmp_path / "take.csv", js.Recording(t=t, x=x))
    assert list(tmp_path.iterdir()) == []


def test_construction_checks_the_arrays():
    t, x = _two_markers()
    with pytest.raises(js.InputError, match="^t: not strictly increasing at frame 2"):
        js.Recording(t=[0.0, 0.5, 0.5], x=x)
    with pytest.raises(js.InputError, match="markers: has 1 names for 2 markers"):
        js.Recording(t=t, x=x, markers=("only",))
    with pytest.raises(js.InputError, match="'a' is used twice"):
        js.Recording(t=t, x=x, markers=("a", "a"))


_T, _X = _two_markers()
_LOST = _X.copy()
_LOST[:, 1] = NAN
_HALF = _X.copy()
_HALF[2, 0, 1] = NAN
_INF = _X.copy()
_INF[2, 1, 0] = np.inf


def _h5_case(attrs=None, **datasets):
    return lambda path: _write_h5(path.with_suffix(".h5"), attrs=attrs, **datasets)


def _bytes_case(suffix, data):
    def make(path):
        path = path.with_suffix(suffix)
        path.write_bytes(data)
        return path

    return make


def _csv_case(text):
    return _bytes_case(".csv", text.encode())


_HEADER = "t,a_x,a_y,a_z\n"
BAD_FILES = {
    "missing": (lambda path: path / "absent.h5", ["file not found"]),
    "folder": (lambda path: path.parent, ["not a file"]),
    "trajectory file": (
        _h5_case({"format": "jaxspring.trajectory", "format_version": 1}, **{"trajectory/x": _X}),
        ["not a jaxspring recording", "jaxspring.trajectory"],
    ),
    "hdf5 without format": (_h5_case({}, t=_T, x=_X), ["not a jaxspring recording", "no format attribute"]),
    "newer version": (_h5_case({"format": "jaxspring.recording", "format_version": 2}, t=_T, x=_X), ["format_version"]),
    "random bytes .h5": (_bytes_case(".h5", bytes(range(256)) * 4), ["not a readable HDF5 file"]),
    "random bytes, no suffix": (_bytes_case(".bin", bytes(range(256)) * 4), ["not a recording"]),
    "no /x": (_h5_case(t=_T), ["/x is missing"]),
    "t not increasing": (_h5_case(t=[0.0, 0.02, 0.01], x=_X), ["t:", "not strictly increasing", "frame 2"]),
    "t not finite": (_h5_case(t=[0.0, NAN, 0.02], x=_X), ["t:", "frame 1", "non-finite"]),
    "one frame": (_h5_case(t=[0.0], x=_X[:1]), ["t:", "fewer than 2"]),
    "x not (F, M, 3)": (_h5_case(t=_T, x=_X[..., :2]), ["x:", "shape (3, 2, 2)"]),
    "x frames differ from t": (_h5_case(t=_T, x=_X[:2]), ["x:", "shape (2, 2, 3)", "3 frames"]),
    "x strings": (_h5_case(t=_T, x=np.array([["a", "b"]] * 3, dtype="S1")), ["x:", "not numbers"]),
    "x infinite": (_h5_case(t=_T, x=_INF), ["x:", "frame 2, marker 'm1' (index 1)", "infinite"]),
    "x partly NaN": (_h5_case(t=_T, x=_HALF), ["x:", "frame 2, marker 'm0' (index 0)", "some coordinates but not all"]),
    "marker never seen": (
        _h5_case(t=_T, x=_LOST, markers=np.array([b"wrist", b"elbow"])),
        ["'elbow'", "not seen in any frame"],
    ),
    "marker names miscounted": (_h5_case(t=_T, x=_X, markers=np.array([b"a"])), ["markers:", "1 names for 2"]),
    "csv first column not t": (_csv_case("time,a_x,a_y,a_z\n0,1,2,3\n1,1,2,3\n"), ["first column", "'time'"]),
    "csv columns not triples": (_csv_case("t,a_x,a_y\n0,1,2\n1,1,2\n"), ["multiple of 3"]),
    "csv triple of two markers": (_csv_case("t,a_x,a_y,b_z\n0,1,2,3\n1,1,2,3\n"), ["a_x,a_y,b_z", "<name>_x"]),
    "csv triple out of order": (_csv_case("t,a_y,a_x,a_z\n0,1,2,3\n1,1,2,3\n"), ["a_y,a_x,a_z"]),
    "csv short row": (_csv_case(_HEADER + "0,1,2,3\n0.1,1,2\n"), ["line 3", "3 cells", "header has 4"]),
    "csv long row": (_csv_case(_HEADER + "0,1,2,3,4\n0.1,1,2,3\n"), ["line 2", "5 cells"]),
    "csv non-numeric": (_csv_case(_HEADER + "0,1,2,3\n0.1,1,two,3\n"), ["line 3", "a_y", "'two'", "not a number"]),
    "csv empty time": (_csv_case(_HEADER + "0,1,2,3\n,1,2,3\n"), ["line 3", "frame time is empty"]),
    "csv invalid utf-8": (_bytes_case(".csv", b"t,a_x,a_y,a_z\n0,1,2,\xff\xfe\n"), ["not UTF-8"]),
    "csv t not increasing": (_csv_case(_HEADER + "0,1,2,3\n0,1,2,3\n"), ["t:", "not strictly increasing"]),
    "csv marker never seen": (_csv_case("t,a_x,a_y,a_z,b_x,b_y,b_z\n0,1,2,3,,,\n1,1,2,3,,,\n"), ["'b'", "not seen"]),
    "csv header only": (_csv_case(_HEADER), ["fewer than 2"]),
    "csv empty": (_csv_case(""), ["empty"]),
}


@pytest.mark.parametrize("case", BAD_FILES)
def test_bad_input_is_one_line_naming_the_problem(tmp_path, case):
    make, words = BAD_FILES[case]
    path = make(tmp_path / "bad")
    with pytest.raises((js.InputError, js.FileFormatError)) as info:
        js.load_recording(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(str(path)), message  # names the file
    assert ";" in message  # ... and a fix after the problem
    for word in words:
        assert word in message, message
