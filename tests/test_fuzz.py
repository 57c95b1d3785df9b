"""Generated hostile inputs: scene TOML, recording and trajectory files (valid files mutated
field by field and truncated), and command lines. The contract for every case: a valid result,
or one `JaxspringError` (exit 2 on the command line) whose message is one line; never another
exception, a hang or a crash. Each test prints how many cases it ran."""

import math
import shutil

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxspring as js
from jaxspring.cli import build_parser

FAST = settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
COUNTS = {}


def _contract(call, name):
    """Run `call`; a JaxspringError must be one line; count the case."""
    COUNTS[name] = COUNTS.get(name, 0) + 1
    try:
        return call()
    except js.JaxspringError as exc:
        assert "\n" not in str(exc), str(exc)
        return None


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("nan" if value != value else ("inf" if value > 0 else "-inf"))
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f'"{k}" = {_toml_value(v)}' for k, v in value.items()) + " }"
    raise TypeError(value)


def _toml(document: dict) -> str:
    lines, tables = [], []
    for key, value in document.items():
        (tables if isinstance(value, dict) else lines).append((key, value))
    text = "".join(f'"{k}" = {_toml_value(v)}\n' for k, v in lines)
    for key, table in tables:
        text += f"[{key}]\n" + "".join(f'"{k}" = {_toml_value(v)}\n' for k, v in table.items())
    return text


SCALARS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.text(max_size=6),
    st.booleans(),
)
VALUES = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=4), max_leaves=12)
CHAIN = {
    "name": "fuzz",
    "dt": 0.001,
    "physics": {"ks": 100.0, "kd": 1.0, "cd": 0.1, "gravity": [0.0, -9.81, 0.0]},
    "lattice": {"shape": [4], "springs": ["structural"], "pinned": [[0]], "drag": True, "mass": 1.0},
}
FIELDS = [("", "dt"), ("", "steps"), ("", "save_every"), ("", "integrator"), ("", "backend")]
FIELDS += [("physics", k) for k in ("ks", "kd", "cd", "gravity", "kg")]
FIELDS += [("lattice", k) for k in ("shape", "springs", "pinned", "spacing", "mass", "axes", "origin", "drag")]


@FAST
@given(st.lists(st.tuples(st.sampled_from(FIELDS), VALUES), min_size=1, max_size=3))
def test_scene_files_with_generated_values(tmp_path_factory, changes):
    document = {k: dict(v) if isinstance(v, dict) else v for k, v in CHAIN.items()}
    for (table, key), value in changes:
        (document.setdefault(table, {}) if table else document)[key] = value
    path = tmp_path_factory.mktemp("scene") / "fuzz.toml"
    path.write_text(_toml(document))
    scene = _contract(lambda: js.load_scene(path), "scene files")
    if scene is not None:
        assert scene.model.particle_count >= 1


@pytest.fixture(scope="module")
def valid_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("valid")
    t = np.linspace(0.0, 0.5, 6)
    js.save_recording(folder / "rec.h5", js.Recording(t=t, x=np.random.default_rng(0).normal(size=(6, 3, 3))))
    scene = js.load_scene("chain")
    traj = js.rollout(scene.model, scene.params, scene.state, steps=20, save_every=10)
    js.save_trajectory(folder / "traj.h5", scene, traj)
    return folder


MUTANTS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**62), max_value=2**62),
    st.text(max_size=5),
    st.lists(st.floats(allow_nan=True), max_size=7).map(np.asarray),
    st.tuples(st.integers(0, 4), st.integers(0, 4), st.integers(1, 3)).map(lambda s: np.zeros(s)),
    st.just(b"bytes"),
    st.just("group"),
)


def _mutate(source, folder, target, value, truncate):
    path = folder / "mutant.h5"
    shutil.copy(source, path)
    if truncate is not None:
        data = path.read_bytes()
        path.write_bytes(data[: int(truncate * len(data))])
        return path
    with h5py.File(path, "r+") as f:
        place, _, name = target.rpartition("/")
        group = f[place] if place else f
        if name.startswith("@"):
            group.attrs[name[1:]] = value
            return path
        if name in group:
            del group[name]
        if isinstance(value, str) and value == "group":
            group.create_group(name)
        else:
            group.create_dataset(name, data=value)
    return path


@FAST
@given(
    st.sampled_from(["t", "x", "markers", "@format", "@format_version"]),
    MUTANTS,
    st.one_of(st.none(), st.floats(0.0, 0.99)),
)
def test_recording_files_mutated_or_truncated(valid_files, tmp_path_factory, target, value, truncate):
    path = _mutate(valid_files / "rec.h5", tmp_path_factory.mktemp("rec"), target, value, truncate)
    _contract(lambda: js.load_recording(path), "recording files")


@FAST
@given(
    st.sampled_from(
        [
            "trajectory/t",
            "trajectory/x",
            "trajectory/v",
            "params/ks",
            "params/gravity",
            "topology/springs",
            "topology/rest_length",
            "topology/mass",
            "topology/pinned",
            "topology/faces",
            "@dt",
            "@integrator",
            "@format_version",
            "topology/@lattice_shape",
        ]
    ),
    MUTANTS,
    st.one_of(st.none(), st.floats(0.0, 0.99)),
)
def test_trajectory_files_mutated_or_truncated(valid_files, tmp_path_factory, target, value, truncate):
    path = _mutate(valid_files / "traj.h5", tmp_path_factory.mktemp("traj"), target, value, truncate)
    _contract(lambda: js.load_trajectory(path), "trajectory files")


WORDS = ["run", "fit", "check", "render", "bench", "predict", "demo", "chain", "--steps", "--save-every", "--dt"]
WORDS += ["--set", "ks=abc", "--out", "-5", "0", "1e999", "nan", "--integrator", "rk5", "--backend", "gpu", "--"]


@FAST
@given(st.lists(st.one_of(st.sampled_from(WORDS), st.text(max_size=8)), max_size=6))
def test_command_lines_parse_or_fail_in_one_line(argv):
    COUNTS["command lines"] = COUNTS.get("command lines", 0) + 1
    parser = build_parser()
    try:
        parser.parse_args(argv)
    except SystemExit as exc:
        assert exc.code in (0, 2), exc.code


INDICES = st.one_of(
    st.integers(min_value=-(2**40), max_value=2**40),
    st.integers(min_value=-8, max_value=8),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.text(max_size=3),
)
INDEX_LISTS = st.one_of(st.lists(INDICES, max_size=5), INDICES)
SIZES = st.one_of(  # small, or far too large (refused before anything is built), or not a count
    st.integers(min_value=-3, max_value=8),
    st.integers(min_value=10**5, max_value=2**62),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.text(max_size=3),
)
TAKES = [
    js.Recording(
        t=np.arange(12) * 0.01,
        x=np.stack([np.linspace(0.0, 0.3, 4), np.zeros(4), np.zeros(4)], -1)[None]
        + 1e-3 * np.arange(12)[:, None, None],
        markers=("a", "b", "c", "d"),
    ),
    js.Recording(
        t=np.arange(9) * 0.01,
        x=np.stack([np.linspace(0.3, 0.0, 4), np.zeros(4), np.zeros(4)], -1)[None] + 1e-3 * np.arange(9)[:, None, None],
        markers=("d", "c", "b", "a"),
    ),
]
ROPE = {
    "name": "rope",
    "dt": 0.002,
    "physics": {"ks": {"stretch": 300.0}, "kd": {"stretch": 0.5}},
    "particles": {"x": [[0.1 * i, 0.0, 0.0] for i in range(4)], "mass": 0.03},
    "springs": [{"name": "stretch", "pairs": [[0, 1], [1, 2], [2, 3]]}],
}


@pytest.fixture(scope="module")
def rope():
    return js.scene_from_dict(ROPE)


@FAST
@given(
    st.fixed_dictionaries(
        {},
        optional={
            "markers": INDEX_LISTS,
            "driven": INDEX_LISTS,
            "start": INDICES,
            "smooth": INDICES,
            "loss": st.sampled_from(["mse", "l1", "huber", "l3", ""]),
            "huber_scale": st.floats(allow_nan=True, allow_infinity=True),
            "fit_start": st.booleans(),
            "fit_driven": st.booleans(),
            "marker_names": st.one_of(st.none(), st.permutations(["a", "b", "c", "d"]), st.lists(st.text(max_size=2))),
        },
    ),
    st.sampled_from([TAKES, TAKES[:1], TAKES[1:]]),
)
def test_recording_targets_with_generated_settings(rope, settings_, takes):
    scene = rope
    target = _contract(lambda: js.recording_target(scene, takes, **settings_), "recording targets")
    if target is not None:  # a valid target: every index in range, each driven particle once, no NaN state
        assert np.all((0 <= target.markers) & (target.markers < 4)) and len(set(target.driven)) == len(target.driven)
        assert np.isfinite(target.states_x).all() and np.isfinite(target.filled).all()
        assert 2 * target.smooth + 1 <= min(r.frame_count for r in takes)


@FAST
@given(
    st.fixed_dictionaries(
        {},
        optional={
            "driven": INDEX_LISTS,
            "subdivide": SIZES,
            "groups": SIZES,
            "reference": st.one_of(st.tuples(INDICES, INDICES), INDICES),
            "rest": st.sampled_from(["data", "straight", "bent"]),
            "bending": st.booleans(),
            "name": st.text(max_size=6),
        },
    )
)
def test_cable_scenes_with_generated_settings(settings_):
    settings_ = {"driven": (0, -1), **settings_}
    cable = _contract(lambda: js.cable_scene(TAKES, **settings_), "cable scenes")
    if cable is not None:  # a valid cable: its scene file parses back, every number finite
        import tomllib

        scene = _contract(lambda: js.scene_from_dict(tomllib.loads(cable.toml())), "cable scenes")
        assert scene is not None
        assert np.isfinite(np.asarray(scene.state.x)).all() and np.isfinite(np.asarray(scene.model.mass)).all()


def test_zz_case_counts(capsys):
    """Printed in the test log (-s or the captured output of a failure): at least 1,500 cases."""
    with capsys.disabled():
        print(f"\nfuzz cases: {COUNTS} (total {sum(COUNTS.values())})")
    assert sum(COUNTS.values()) >= 1500
