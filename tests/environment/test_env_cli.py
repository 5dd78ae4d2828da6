"""``density-planner env``: files written for each source, one-line errors without tracebacks, import
hygiene."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch
from PIL import Image

from density_planner.cli import main
from density_planner.environment import load_scene, random_scene


def test_random(tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["env", "--kind", "random", "--seed", "3", "--out", str(out)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.count("\n") == 0 and "random-3" in line
    scene = load_scene(out / "occupancy.npz")
    assert torch.equal(scene.grid.probs, random_scene(3).grid.probs)
    info = json.loads((out / "scene.json").read_text())
    assert info["start"] == [0.0, -28.0, 1.5, 3.0] and info["goal"] == [0.0, 8.0]
    assert info["grid"]["shape"] == [101, 241, 401]
    with Image.open(out / "occupancy.png") as im:
        assert im.size[0] > 400
    with Image.open(out / "occupancy.gif") as gif:
        assert gif.n_frames == 51  # every 2nd of 101 slices
    assert (out / "occupancy.gif").stat().st_size < 5 * 2**20


def test_set_and_config_file(tmp_path):
    cfg = tmp_path / "env.toml"
    cfg.write_text("[random_scene]\nn_slices = 11\n")
    out = tmp_path / "r"
    assert (
        main(
            [
                "env",
                "--kind",
                "random",
                "--config",
                str(cfg),
                "--set",
                "random_scene.n_dynamic=[0, 0]",
                "--no-gif",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    scene = load_scene(out / "occupancy.npz")
    assert scene.grid.n_slices == 11
    assert all(o["kind"] != "dynamic" for o in scene.meta["obstacles"])
    assert not (out / "occupancy.gif").exists()


def test_ind(ind_dir, tmp_path):
    out = tmp_path / "i"
    assert (
        main(
            [
                "env",
                "--kind",
                "ind",
                "--data-dir",
                str(ind_dir),
                "--recording",
                "7",
                "--start-time",
                "2",
                "--seed",
                "1",
                "--no-gif",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    scene = load_scene(out / "occupancy.npz")
    assert scene.grid.t0 == 2.0 and scene.meta["recording"] == 7 and scene.meta["config"]["seed"] == 1


def test_commonroad(commonroad_dir, tmp_path):
    pytest.importorskip("commonroad", reason="commonroad-io (extra 'commonroad') is not installed")
    out = tmp_path / "c"
    assert (
        main(
            [
                "env",
                "--kind",
                "commonroad",
                "--file",
                str(commonroad_dir / "USA_Peach-4_8_T-1.xml"),
                "--no-gif",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert load_scene(out / "occupancy.npz").name == "USA_Peach-4_8_T-1.xml"
    assert load_scene(out / "occupancy.npz").road is not None


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["--kind", "ind", "--data-dir", "{tmp}/none", "--recording", "1"], "inD file not found"),
        (["--kind", "ind", "--data-dir", "{tmp}"], "needs --data-dir D and --recording N"),
        (["--kind", "commonroad"], "needs --file"),
        (["--kind", "commonroad", "--file", "{tmp}/bad.xml"], "not a CommonRoad scenario"),
        (["--kind", "random", "--set", "random_scene.walls=3"], "unknown key"),
        (["--kind", "random", "--file", "x.xml"], "not used with --kind random"),
        (["--kind", "random", "--seed", "-2"], "--seed must be an integer in [0, 2^63 - 1]"),
    ],
)
def test_errors_are_one_line_without_traceback(tmp_path, capsys, args, match):
    (tmp_path / "bad.xml").write_text("<root/>")
    if "commonroad" in args and "--file" in args:
        pytest.importorskip("commonroad", reason="commonroad-io (extra 'commonroad') is not installed")
    argv = [
        "env",
        *[a.replace("{tmp}", str(tmp_path)) for a in args],
        "--no-gif",
        "--out",
        str(tmp_path / "o"),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.startswith("density-planner: error:") and err.count("\n") == 1
    assert match in err


def test_environment_does_not_import_matplotlib():
    code = (
        "import sys, density_planner.environment as e; e.random_scene(0); print('matplotlib' in sys.modules)"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"


def test_missing_commonroad_extra_is_a_clear_error(tmp_path, capsys, monkeypatch):
    # simulate an installation without the 'commonroad' extra
    monkeypatch.setitem(sys.modules, "commonroad", None)
    monkeypatch.setitem(sys.modules, "commonroad.common.file_reader", None)
    (tmp_path / "s.xml").write_text("<commonRoad/>")
    argv = ["env", "--kind", "commonroad", "--file", str(tmp_path / "s.xml"), "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "commonroad-io" in err and "density-planner[commonroad]" in err and "Traceback" not in err
