import json
import re

import numpy as np
import open3d as o3d
import pytest
from click.testing import CliRunner
from scipy.spatial import cKDTree

from o3dsoft.cli.main import main
from o3dsoft.io import read_points, read_transform, write_points, write_transform

from .conftest import EXAMPLES, apply, blob, georeferenced_bunny, random_transform


@pytest.fixture
def pair_files(tmp_path):
    rng = np.random.default_rng(0)
    src = blob(rng, 400)
    T = random_transform(rng, max_angle=6.0, max_t=0.1)
    write_points(tmp_path / "src.ply", src)
    write_points(tmp_path / "tgt.pcd", apply(T, src))
    write_transform(tmp_path / "gt.txt", T)
    return tmp_path, src, T


def run(*args):
    result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return result


def test_help_and_version():
    for cmd in ([], ["register"], ["train"], ["bench"]):
        r = run(*cmd, "--help")
        assert r.exit_code == 0 and "Usage:" in r.output
    r = run("--version")
    assert r.exit_code == 0 and "o3dsoft, version" in r.output


def test_register_table_with_ground_truth_and_outputs(pair_files, tiny_model_path):
    d, src, T = pair_files
    r = run(
        "register",
        d / "src.ply",
        d / "tgt.pcd",
        "--weights",
        tiny_model_path,
        "--gt",
        d / "gt.txt",
        "--icp-distance",
        "0.5",
        "--out",
        d / "aligned.xyz",
        "--save-transform",
        d / "T.txt",
        "--render",
        d / "fig.png",
    )
    assert r.exit_code == 0, r.output
    assert "T_target_source" in r.output and "higher is better" in r.output and "lower is better" in r.output
    assert "network + ICP" in r.output and "deg" in r.output
    assert "|R-Rgt|_1, |R-Rgt|_2: entrywise L1 and Frobenius norms of the rotation matrices' difference, no unit" in r.output
    assert "constraint   not measured: the clouds share their points" in r.output  # the target is the source moved
    assert re.search(r"estimate     from the [a-zA-Z -]+(, refined by ICP)?\n", r.output)  # "from the network starts", not "the network starts's"
    assert np.allclose(read_transform(d / "T.txt"), T, atol=1e-5)
    assert np.allclose(read_points(d / "aligned.xyz"), apply(T, src), atol=1e-4)
    assert (d / "fig.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and re.search(rf"Picture: {re.escape(str(d / 'fig.png'))} \(\d+ ms\)", r.output)
    assert re.search(rf"Aligned source: {re.escape(str(d / 'aligned.xyz'))} \(\d+ ms\)", r.output) and f"Transform: {d / 'T.txt'}" in r.output
    assert "(not counted: the program's start-up and imports; the outputs asked for are timed on their own lines)" in r.output


def test_register_names_a_ground_truth_the_other_way_round(pair_files, tiny_model_path):
    d, _, T = pair_files
    write_transform(d / "inverse.txt", np.linalg.inv(T))
    notes = []
    for gt in ("gt.txt", "inverse.txt"):
        r = run("register", d / "src.ply", d / "tgt.pcd", "--weights", tiny_model_path, "--gt", d / gt, "--icp-distance", "0.5")
        assert r.exit_code == 0, r.output
        notes.append("it may map the target onto the source; --gt takes T_target_source" in r.output)
    assert notes == [False, True]  # the right result is twice the pair's turn from the inverse (2 x 4.7 degrees)


def test_the_aligned_source_keeps_its_colours_and_normals(pair_files, tiny_model_path):
    d, src, T = pair_files
    colors = np.random.default_rng(3).random(src.shape)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    cloud.colors = o3d.utility.Vector3dVector(colors)
    cloud.estimate_normals()
    normals = np.asarray(cloud.normals).copy()
    o3d.io.write_point_cloud(str(d / "coloured.ply"), cloud)
    r = run("register", d / "coloured.ply", d / "tgt.pcd", "--weights", tiny_model_path, "--out", d / "aligned.ply", "--save-transform", d / "T.txt")
    assert r.exit_code == 0, r.output
    aligned, R = o3d.io.read_point_cloud(str(d / "aligned.ply")), read_transform(d / "T.txt")[:3, :3]
    assert np.allclose(np.asarray(aligned.points), apply(read_transform(d / "T.txt"), src))
    assert np.abs(np.asarray(aligned.colors) - colors).max() <= 0.5 / 255 + 1e-9  # 8-bit, as the file held them
    assert np.allclose(np.asarray(aligned.normals), normals @ R.T)  # turned with the points


def test_register_says_how_many_isolated_points_it_left_out(tmp_path):
    from .conftest import EXAMPLES

    rng = np.random.default_rng(0)
    files = []
    for name in ("bun045", "bun000"):
        points = read_points(EXAMPLES / f"{name}.ply")
        files.append(write_points(tmp_path / f"{name}.ply", np.vstack([points, rng.uniform(points.min(0), points.max(0), (len(points) // 10, 3))])))
    r = run("register", *files, "--voxel", "0.004")
    assert r.exit_code == 0, r.output
    assert re.search(
        r"isolated: source \d+, target \d+ points left out \(fewer than two other points within 3 voxels: scattered outliers, or the sparsest far returns\)",
        r.output,
    )

    # The legend gives the thresholds of the settings in use.
    from dataclasses import replace

    import o3dsoft
    from o3dsoft.cli.main import _format_result

    config = o3dsoft.RegisterConfig()
    config = replace(config, degeneracy=replace(config.degeneracy, min_constraint=0.0031, max_flatness=0.77))
    result = o3dsoft.register(read_points(files[0]), read_points(files[1]), config)
    text = _format_result("a.ply", "b.ply", result, None, {"path": "model.pt"}, config)
    assert "below 0.0031: not determined" in text and "from 0.77: not determined" in text


def test_register_says_how_many_points_cleaning_dropped_and_why(pair_files, tiny_model_path):
    d, src, T = pair_files
    write_points(d / "glitch.ply", np.vstack([src, [[1e12, -1e12, 5e11]]]))
    r = run("register", d / "glitch.ply", d / "tgt.pcd", "--weights", tiny_model_path, "--icp-distance", "0.5")
    assert r.exit_code == 0, r.output
    assert "strays: source 1, target 0 points dropped (over 2,000 times farther from the median than 90 % of the cloud)" in r.output
    r = run("register", d / "src.ply", d / "tgt.pcd", "--weights", tiny_model_path, "--icp-distance", "0.5")
    assert r.exit_code == 0 and "strays:" not in r.output and "non-finite:" not in r.output and "duplicates:" not in r.output
    holes = np.vstack([src, np.full((3, 3), np.nan), src[:5]])  # an organised scan's empty pixels, and points written twice
    write_points(d / "holes.ply", holes)
    r = run("register", d / "holes.ply", d / "tgt.pcd", "--weights", tiny_model_path, "--icp-distance", "0.5")
    assert r.exit_code == 0, r.output
    assert "non-finite: source 3, target 0 rows dropped (a NaN or infinite coordinate)" in r.output
    assert "duplicates: source 5, target 0 repeated points dropped (kept once)" in r.output


def test_register_measures_the_errors_of_georeferenced_clouds_about_the_target(tmp_path):
    # About the frame's origin, 4e6 units away, the bunny's 0.07 degrees of rotation error would
    # move it by 5,000 units: the translation errors are taken about the target, as registered;
    # and the truth's rotation, rounded to 6 decimals, is made exact about the source.
    source, target, _ = georeferenced_bunny(tmp_path)
    r = CliRunner().invoke(main, ["register", str(source), str(target), "--gt", str(tmp_path / "gt.txt"), "--json", "--out", str(tmp_path / "a.pcd")])
    assert r.exit_code == 0, r.output
    final = json.loads(r.stdout)["errors"]["final"]
    assert 0.01 < final["rotation_deg"] < 1.0 and final["translation"] < 0.002  # the bunny is 0.2 units across
    # The aligned source in PCD: float32 would round it by up to 0.25 units there.
    assert "holds x, y, z as float64" in r.stderr
    aligned, goal = read_points(tmp_path / "a.pcd"), read_points(target)
    assert np.median(cKDTree(goal).query(aligned)[0]) < 0.001


def test_an_error_o3dsoft_does_not_check_for_is_one_line_unless_a_traceback_is_asked(pair_files, tiny_model_path, monkeypatch):
    import o3dsoft.pipeline

    def fails(*args, **kwargs):
        raise RuntimeError("\x1b[1;31m[Open3D Error] (VoxelDownSample) voxel_size is too small.\x1b[0;m\nmore detail")

    monkeypatch.setattr(o3dsoft.pipeline, "register", fails)
    d, _, _ = pair_files
    args = ["register", d / "src.ply", d / "tgt.pcd", "--weights", tiny_model_path]
    r = run(*args)
    assert r.exit_code == 1 and "Traceback" not in r.output
    assert r.output.startswith("Error: RuntimeError: [Open3D Error] (VoxelDownSample) voxel_size is too small. (please report it")
    assert len(r.output.strip().splitlines()) == 1
    monkeypatch.setenv("O3DSOFT_TRACEBACK", "1")
    with pytest.raises(RuntimeError, match="voxel_size is too small"):
        run(*args)


def test_register_json(pair_files, tiny_model_path):
    d, _, T = pair_files
    r = run("register", d / "src.ply", d / "tgt.pcd", "--weights", tiny_model_path, "--gt", d / "gt.txt", "--json", "--icp-distance", "0.5")
    assert r.exit_code == 0, r.output
    payload = json.loads(r.output)
    assert np.allclose(payload["transformation"], T, atol=1e-5)
    assert payload["errors"]["final"]["rotation_deg"] < 1e-3
    assert payload["constraint"] is None and payload["flatness"] is None  # shared points: not measured
    assert {"fitness", "inlier_rmse", "confidence", "likely_failed", "coarse_transformation", "timings_ms"} <= set(payload)
    assert payload["likely_failed"] is False
    # The printed result reads back into the library's, as it was.
    from o3dsoft.errors import InputError
    from o3dsoft.pipeline import RegistrationResult

    again = RegistrationResult.from_dict(payload)
    assert again.transformation.dtype == np.float64 and np.array_equal(again.transformation, np.array(payload["transformation"]))
    assert json.loads(json.dumps(again.to_dict())) == {k: v for k, v in payload.items() if k not in ("source", "target", "model", "errors")}
    with pytest.raises(InputError, match="not a registration result: no transformation"):
        RegistrationResult.from_dict({k: v for k, v in payload.items() if k != "transformation"})
    with pytest.raises(InputError, match="coarse_transformation: expected a 4x4 transform, got shape \\(3, 4\\)"):
        RegistrationResult.from_dict({**payload, "coarse_transformation": payload["coarse_transformation"][:3]})
    # Hand-edited or other tools' JSON: each field holds its own type, or it is refused by name.
    for field, value, message in (
        ("likely_failed", "false", "likely_failed must be True or False, got 'false'"),
        ("confidence", "high", "confidence must be a number, got 'high'"),
        ("transformation", None, "transformation must not be None"),
        ("fitness", None, "fitness must not be None"),
        ("timings_ms", None, "timings_ms must be a mapping, got None"),
        ("confidence", 7.0, r"confidence must be in \[0, 1\], got 7.0"),
        ("fitness", float("nan"), r"fitness must be in \[0, 1\], got nan"),
        ("transformation", np.diag([2.0, 1.0, 1.0, 1.0]).tolist(), "transformation: not a rigid transform"),
    ):
        with pytest.raises(InputError, match=message):
            RegistrationResult.from_dict({**payload, field: value})


def test_likely_failure_warns_and_strict_exits_3(tmp_path, tiny_model_path):
    rng = np.random.default_rng(5)
    write_points(tmp_path / "blob.ply", blob(rng, 500))
    write_points(tmp_path / "slab.ply", rng.uniform(-1, 1, size=(500, 3)) * np.array([1.0, 1.0, 0.05]))
    args = ["register", tmp_path / "blob.ply", tmp_path / "slab.ply", "--weights", tiny_model_path]
    r = CliRunner().invoke(main, [str(a) for a in args + ["--json"]])
    assert r.exit_code == 0 and "likely wrong" in r.stderr
    assert json.loads(r.stdout)["likely_failed"] is True
    r = CliRunner().invoke(main, [str(a) for a in args + ["--strict", "--out", tmp_path / "moved.ply", "--save-transform", tmp_path / "T.txt"]])
    assert r.exit_code == 3 and "LIKELY FAILED" in r.stdout and "Not written (--strict, the result is flagged): --out, --save-transform" in r.stderr
    assert not (tmp_path / "moved.ply").exists() and not (tmp_path / "T.txt").exists()  # nothing a pipeline could pick up


def test_search_options_reach_the_pipeline(pair_files, tiny_model_path, monkeypatch):
    from o3dsoft import pipeline

    d, _, _ = pair_files
    seen = []
    real = pipeline.register
    monkeypatch.setattr(pipeline, "register", lambda *args, **kwargs: seen.append(args[2]) or real(*args, **kwargs))
    for flags in ([], ["--search-restart", "--no-search-features", "--search-feature-stop", "0.9"]):
        r = run("register", d / "src.ply", d / "tgt.pcd", "--weights", tiny_model_path, "--json", *flags)
        assert r.exit_code == 0, r.output
    assert [(c.search.restart.enabled, c.search.features.enabled, c.search.features.stop) for c in seen] == [(False, True, 0.5), (True, False, 0.9)]
    r = run("register", d / "src.ply", d / "tgt.pcd", "--weights", tiny_model_path, "--search-feature-stop", "0.3")
    assert r.exit_code == 2 and "0.3 is not in the range 0.5<=x<=1.0" in r.output


def test_no_refine(pair_files, tiny_model_path):
    d, _, _ = pair_files
    r = run("register", d / "src.ply", d / "tgt.pcd", "--weights", tiny_model_path, "--no-refine", "--json")
    payload = json.loads(r.output)
    assert payload["transformation"] == payload["coarse_transformation"]


@pytest.mark.parametrize(
    "make,args,code,message",
    [
        (None, ["missing.ply", "tgt.pcd"], 2, "missing.ply: no such file"),
        (lambda d: (d / "a.abc").write_text("1 2 3"), ["a.abc", "tgt.pcd"], 2, "unknown extension '.abc'"),
        (lambda d: (d / "e.xyz").write_text(""), ["e.xyz", "tgt.pcd"], 1, "e.xyz: parsed to 0 points"),
        (lambda d: (d / "few.xyz").write_text("0 0 0\n1 0 0\n0 1 0\n"), ["few.xyz", "tgt.pcd"], 1, "few.xyz: 3 distinct finite points; at least 8"),
        (lambda d: (d / "nan.xyz").write_text("nan 0 0\n" * 20), ["nan.xyz", "tgt.pcd"], 1, "nan.xyz: 0 distinct finite points"),
        (lambda d: (d / "same.xyz").write_text("1 1 1\n" * 20), ["same.xyz", "tgt.pcd"], 1, "same.xyz: 1 distinct finite points"),
        (lambda d: (d / "line.xyz").write_text("".join(f"{i} {i} 0\n" for i in range(20))), ["line.xyz", "tgt.pcd"], 1, "line.xyz: all points lie on one line"),
        (lambda d: (d / "m.off").write_text("OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n"), ["m.off", "tgt.pcd"], 1, "m.off: mesh has 3 vertices but no faces"),
        (
            lambda d: (d / "bad.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 q 0\n0 0 0 1\n"),
            ["src.ply", "tgt.pcd", "--gt", "bad.txt"],
            1,
            "bad.txt, line 3: 'q' is not a number",
        ),
        (
            lambda d: (d / "skew.txt").write_text("1 1 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"),
            ["src.ply", "tgt.pcd", "--gt", "skew.txt"],
            1,
            "skew.txt: not a rigid transform",
        ),
        (
            lambda d: (d / "skew.txt").write_text("1 1 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"),
            ["src.ply", "tgt.pcd", "--init", "skew.txt"],
            1,
            "skew.txt: not a rigid transform",
        ),
        (lambda d: (d / "w.pt").write_bytes(b"junk"), ["src.ply", "tgt.pcd", "--weights", "w.pt"], 1, "w.pt: not a readable TorchScript model file"),
        (None, ["src.ply", "tgt.pcd", "--out", "no_dir/out.ply"], 1, "folder no_dir does not exist"),
        (None, ["src.ply", "tgt.pcd", "--out", "/proc/out.ply"], 1, "/proc/out.ply: cannot create a file in folder /proc"),  # before the work
        (None, ["src.ply", "tgt.pcd", "--out", "out.off"], 2, "unknown extension '.off'"),
        (None, ["src.ply", "tgt.pcd", "--points", "0"], 2, "Invalid value for '--points'"),
        (None, ["src.ply", "tgt.pcd", "--points", "4"], 2, "num_points=4 is below the network's neighbourhood size"),
        (None, ["src.ply", "tgt.pcd", "--weights", "missing.pt"], 2, "missing.pt: weights file not found"),
        (lambda d: (d / "wdir").mkdir(), ["src.ply", "tgt.pcd", "--weights", "wdir"], 2, "wdir: is a folder; expected a model file"),
        (lambda d: (d / "scans").mkdir(), ["scans", "tgt.pcd"], 2, "scans: is a folder, not a file"),
        (lambda d: (d / "odir").mkdir(), ["src.ply", "tgt.pcd", "--out", "odir"], 2, "--out odir: is a folder; give a file name"),
        (lambda d: (d / "tdir").mkdir(), ["src.ply", "tgt.pcd", "--save-transform", "tdir"], 2, "tdir: cannot write, it is a folder"),
        (None, ["src.ply", "tgt.pcd", "--second-weights", "incongruant"], 2, "incongruant: weights file not found (shipped models, by name:"),
        (lambda d: (d / "v.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"), ["v.obj", "tgt.pcd"], 1, "v.obj: mesh has 4 vertices but no faces"),
        (None, ["src.ply", "tgt.pcd", "--device", "tpu9"], 2, "invalid device 'tpu9'"),
        (None, ["src.ply", "tgt.pcd", "--max-rotation", "270"], 2, "Invalid value for '--max-rotation'"),
        (None, ["src.ply", "tgt.pcd", "--max-rotation", "nan"], 2, "Invalid value for '--max-rotation': nan is not a finite number"),
        (None, ["src.ply", "tgt.pcd", "--voxel", "inf"], 2, "Invalid value for '--voxel': inf is not a finite number"),
        (None, ["src.ply", "tgt.pcd", "--icp-absolute"], 2, "--icp-absolute needs --icp-distance, in the clouds' units"),
        (None, ["src.ply", "tgt.pcd", "--render", "fig.txt"], 2, "--render fig.txt: give a .png file name"),
        (None, ["src.ply", "tgt.pcd", "--save-transform", "T.ply"], 2, "--save-transform T.ply: a transform is written as text (.txt) or .npy, not as .ply"),
        (None, ["src.ply", "tgt.pcd", "--save-transform", "T.json"], 2, "not as .json (--json prints the whole result as JSON)"),
        (None, ["src.ply", "tgt.pcd", "--second-turns", "24"], 2, "Invalid value for '--second-turns'"),
    ],
)
def test_bad_input_clear_error_no_traceback_no_output(pair_files, tiny_model_path, monkeypatch, make, args, code, message):
    d, _, _ = pair_files
    monkeypatch.chdir(d)
    if make is not None:
        make(d)
    before = set(p.name for p in d.rglob("*"))
    extra = [] if "--weights" in args else ["--weights", str(tiny_model_path)]
    r = CliRunner().invoke(main, ["register", *args, *extra])
    assert r.exit_code == code, r.output
    assert message in r.output
    assert "Traceback" not in r.output
    assert set(p.name for p in d.rglob("*")) == before  # nothing half-written


def test_bench_lists_its_commands():
    r = run("bench", "--help")
    assert r.exit_code == 0 and "modelnet40" in r.output and "bunny" in r.output


def test_voxel_option_downsamples_scans_before_registering():
    from .conftest import EXAMPLES

    r = CliRunner().invoke(
        main,
        [
            "register",
            str(EXAMPLES / "bun045.ply"),
            str(EXAMPLES / "bun000.ply"),
            "--voxel",
            "0.004",
            "--icp-distance",
            "0.04",
            "--icp-absolute",
            "--gt",
            str(EXAMPLES / "bun045_to_bun000.txt"),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert out["num_source"] < 6804 / 2  # 2 mm demo scans on a 4 mm grid
    assert out["errors"]["final"]["rotation_deg"] < 1.0 and out["errors"]["final"]["translation"] < 0.002
    r = CliRunner().invoke(main, ["register", str(EXAMPLES / "bun045.ply"), str(EXAMPLES / "bun000.ply"), "--voxel", "1"])
    assert r.exit_code == 1 and re.search(r"\d+ points? left on a voxel grid of 1 units", r.output) and "Traceback" not in r.output


def test_max_rotation_option_reaches_the_library(pair_files, tiny_model_path):
    d, _, _ = pair_files
    r = CliRunner().invoke(
        main, ["register", str(d / "src.ply"), str(d / "tgt.pcd"), "--weights", str(tiny_model_path), "--max-rotation", "0.001", "--search", "off", "--json"]
    )
    # the test pair is rotated by more than 0.001 degrees: ICP leaves the bound from anywhere in it,
    # so the pose as given comes back, flagged
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["confidence"] == 0.0 and out["likely_failed"]
    assert np.allclose(out["transformation"], np.eye(4))
    assert "ICP leaves the 0.001 degrees of max_rotation (--max-rotation)" in r.output  # the warning on stderr says why


def test_cli_search_modes_and_methods_match_the_library():
    from o3dsoft.bench import METHODS
    from o3dsoft.cli.main import METHOD_NAMES
    from o3dsoft.cli.main import SEARCH_MODES as cli_modes
    from o3dsoft.pipeline import SEARCH_MODES

    assert cli_modes == SEARCH_MODES
    assert METHOD_NAMES == tuple(METHODS)


def test_help_and_version_load_neither_torch_nor_open3d():
    import subprocess
    import sys

    code = (
        "import sys\nfrom o3dsoft.cli.main import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        "print(sorted(m for m in ('torch', 'open3d') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "[]"
    # The library's names still load on first use.
    out = subprocess.run(
        [sys.executable, "-c", "import o3dsoft; print(o3dsoft.register.__module__, 'torch' in __import__('sys').modules)"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert out.split() == ["o3dsoft.pipeline", "True"]


def test_weights_help_names_every_shipped_model():
    from o3dsoft.cli.main import WEIGHTS_HELP
    from o3dsoft.coarse import bundled_model_names

    assert all(f" {name}" in WEIGHTS_HELP.split("(")[0] for name in bundled_model_names())


def test_register_and_the_bench_commands_take_the_same_pipeline_options():
    import inspect

    from o3dsoft.cli import main as cli
    from o3dsoft.pipeline import RegisterConfig

    names = {p.name for p in cli._pipeline_options(lambda: None).__click_params__}
    # each option is read by the one function that turns them into the library's RegisterConfig
    assert names == set(inspect.signature(cli._register_config).parameters) - {"more"}
    for command, args in (
        (main.commands["register"], ["a.ply", "b.ply"]),
        (main.commands["bench"].commands["modelnet40"], []),
        (main.commands["bench"].commands["bunny"], []),
    ):
        values = command.make_context(command.name, args).params
        assert names <= set(values), command.name
        # given nothing, the command line's settings are the library's defaults
        assert cli._register_config(**{n: values[n] for n in names}) == RegisterConfig(), command.name


def test_sigterm_while_writing_the_output_leaves_nothing(pair_files, monkeypatch):
    import os
    import signal

    import o3dsoft.io as io_module

    folder, _, _ = pair_files
    before = sorted(p.name for p in folder.iterdir())
    monkeypatch.setattr(io_module, "_sync", lambda path: os.kill(os.getpid(), signal.SIGTERM))  # the file written, not yet renamed
    r = CliRunner().invoke(main, ["register", str(folder / "src.ply"), str(folder / "tgt.pcd"), "--out", str(folder / "aligned.ply")])
    assert r.exit_code == 130 and "Interrupted" in r.output
    assert sorted(p.name for p in folder.iterdir()) == before  # neither aligned.ply nor its hidden temporary
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # the handler is the command's only


CUT_PLY = b"ply\nformat binary_little_endian 1.0\nelement vertex 500\nproperty float x\nproperty float y\nproperty float z\nend_header\n" + bytes(3000)


@pytest.mark.parametrize("content", [b"", b"ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nend_header\n1\n", b"\x00garbage\xff" * 50, CUT_PLY])
def test_a_broken_ply_file_is_one_line_on_stderr(tmp_path, content):
    """Open3D's PLY reader prints its own "RPly: ..." lines from C; only o3dsoft's line remains."""
    import subprocess
    import sys

    (tmp_path / "bad.ply").write_bytes(content)
    write_points(tmp_path / "good.ply", blob(np.random.default_rng(0), 100))
    r = subprocess.run([sys.executable, "-m", "o3dsoft.cli.main", "register", "bad.ply", "good.ply"], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.startswith("Error: bad.ply") and len(r.stderr.strip().splitlines()) == 1, r.stderr
    if content == CUT_PLY:  # not read as 500 points, 250 of them zeros
        assert "declares 500 vertices, but the file ends after 250" in r.stderr


@pytest.mark.parametrize(
    "outputs, message",
    [
        (["--out", "tgt.pcd"], "tgt.pcd (--out): the same file as TARGET"),
        (["--out", "./sub/../src.ply"], "src.ply (--out): the same file as SOURCE"),
        (["--save-transform", "gt.txt"], "gt.txt (--save-transform): the same file as --gt"),
        (["--out", "a.npy", "--save-transform", "a.npy"], "a.npy (--save-transform): the same file as --out"),
        (["--out", "link.ply"], "link.ply (--out): the same file as SOURCE"),
    ],
)
def test_an_output_over_an_input_is_refused_before_the_work(pair_files, tiny_model_path, outputs, message):
    d, _, _ = pair_files
    (d / "sub").mkdir()
    (d / "link.ply").symlink_to(d / "src.ply")
    before = {p.name: p.read_bytes() for p in d.iterdir() if p.is_file()}
    r = CliRunner().invoke(
        main,
        [
            "register",
            str(d / "src.ply"),
            str(d / "tgt.pcd"),
            "--gt",
            str(d / "gt.txt"),
            "--weights",
            str(tiny_model_path),
            *[str(d / o) if "." in o else o for o in outputs],
        ],
    )
    assert r.exit_code == 2 and message in r.output, r.output
    assert {p.name: p.read_bytes() for p in d.iterdir() if p.is_file()} == before


def test_outputs_are_checked_before_the_work_and_a_failed_write_keeps_the_result(pair_files, tiny_model_path, monkeypatch):
    import o3dsoft.pipeline as pipeline_module

    d, _, _ = pair_files
    monkeypatch.chdir(d)
    calls = []
    real = pipeline_module.register
    monkeypatch.setattr(pipeline_module, "register", lambda *a, **k: calls.append(1) or real(*a, **k))
    base = ["register", "src.ply", "tgt.pcd", "--weights", str(tiny_model_path)]
    r = CliRunner().invoke(main, [*base, "--out", "aligned.ply", "--save-transform", "no_dir/T.txt"])
    assert r.exit_code == 1 and "no_dir/T.txt: cannot write, folder no_dir does not exist" in r.output
    assert calls == [] and not (d / "aligned.ply").exists()  # no registration ran, nothing written

    import o3dsoft.io as io_module
    from o3dsoft.errors import InputError

    def full(path, T):
        raise InputError(f"{path}: cannot write (No space left on device)")

    monkeypatch.setattr(io_module, "write_transform", full)
    r = CliRunner().invoke(main, [*base, "--save-transform", "T.txt"])
    assert r.exit_code == 1 and "T_target_source" in r.output and "No space left on device" in r.output  # the result was printed first


def test_register_help_lists_only_the_formats_it_writes():
    import re

    text = CliRunner().invoke(main, ["register", "--help"]).output
    listed = set(re.findall(r"\.(ply|pcd|xyzrgb|xyzn|xyz|pts|npy)\b", text.split("--out", 1)[1].split("--save-transform", 1)[0]))
    assert listed == {"ply", "pcd", "xyz", "xyzn", "pts", "npy"}


def test_a_result_the_fit_does_not_trust_is_flagged_for_the_fit_not_the_geometry():
    # The bunny pair lies 34 degrees apart: a prior of 10 leaves the pose as given, which also
    # fits about as well turned (the geometry's test, meaningless at a pose that does not fit).
    r = CliRunner().invoke(main, ["register", str(EXAMPLES / "bun045.ply"), str(EXAMPLES / "bun000.ply"), "--max-rotation", "10", "--json"])
    assert r.exit_code == 0, r.output
    result = json.loads(r.stdout)
    assert result["likely_failed"] and result["failure_reason"].startswith("ICP leaves the 10 degrees of max_rotation (--max-rotation) from every estimate")


def test_register_from_an_initial_guess(tmp_path):
    import shutil

    from o3dsoft.transforms import euler_to_matrix, rigid

    for name in ("bun045.ply", "bun000.ply", "bun045_to_bun000.txt"):
        shutil.copy(EXAMPLES / name, tmp_path / name)
    T = read_transform(tmp_path / "bun045_to_bun000.txt")
    write_transform(tmp_path / "guess.txt", rigid(euler_to_matrix([5.0, 5.0, -5.0]) @ T[:3, :3], T[:3, 3] + 0.003))
    args = ["register", tmp_path / "bun045.ply", tmp_path / "bun000.ply", "--init", tmp_path / "guess.txt", "--gt", tmp_path / "bun045_to_bun000.txt"]
    r = run(*args)
    assert r.exit_code == 0, r.output
    assert "estimate     from the initial guess, refined by ICP" in r.output
    out = json.loads(run(*args, "--json").output)
    assert out["estimate_from"] == "initial guess" and out["errors"]["final"]["rotation_deg"] < 1.0
    assert np.allclose(out["init"], read_transform(tmp_path / "guess.txt"))
    r = run("register", "--pairs", tmp_path / "p.txt", "--init", tmp_path / "guess.txt", "--out", tmp_path / "r.csv")
    assert r.exit_code == 2 and "--init belong(s) to a single pair" in r.output


def test_an_error_a_library_raises_for_ctrl_c_is_an_interrupt(pair_files, monkeypatch):
    """Ctrl-C while Open3D imports makes its import fail ("ImportError: initialization failed"):
    the command reports the interrupt, not an error to report as a bug."""
    import os
    import signal
    import time

    import o3dsoft.coarse

    def interrupted_import(*args, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(60)  # the handler raises at once
        except KeyboardInterrupt:
            raise ImportError("initialization failed") from None
        raise AssertionError("no interrupt arrived")

    monkeypatch.setattr(o3dsoft.coarse, "load_model", interrupted_import)
    # As in a terminal: a run started in the background (CI's) inherits SIGINT ignored, which the command respects.
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        folder, _, _ = pair_files
        r = CliRunner().invoke(main, ["register", str(folder / "src.ply"), str(folder / "tgt.pcd")])
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, before)
    assert r.exit_code == 130 and r.output.strip() == "Interrupted.", r.output


@pytest.mark.parametrize("by, words", [("KISS-Matcher", "from KISS-Matcher, refined by ICP"), ("feature match", "from the feature match, refined by ICP")])
def test_the_estimate_line_names_where_it_came_from(pair_files, tiny_model_path, by, words):
    from dataclasses import replace

    from o3dsoft.cli.main import _format_result
    from o3dsoft.config import RegisterConfig
    from o3dsoft.pipeline import register as run_register

    _, src, T = pair_files
    config = RegisterConfig(weights=str(tiny_model_path))
    result = replace(run_register(src, apply(T, src), config), estimate_from=by)
    text = _format_result("src.ply", "tgt.ply", result, None, {"path": "model.pt", "trained": {}}, config)
    assert f"  estimate     {words}\n" in text
