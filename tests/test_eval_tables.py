"""Smoke tests of ``python -m eval tables`` (in-process, tiny renders)."""

from __future__ import annotations

import json

import pytest

from eval.__main__ import main
from eval.tables import PAPER_CARLA, PAPER_CVC12, format_table, markdown_table


def test_tables_quick(tmp_path, capsys, check_environment):
    out = tmp_path / "tables"
    rc = main(["tables", "--quick", "--size", "48", "160", "--pairs", "1", "--no-kitti", "--out", str(out),
               "--no-progress"])
    assert rc == 0
    data = json.loads((out / "tables.json").read_text())
    assert set(data) == {"settings", "cvc12", "carla", "environment"}
    check_environment(data["environment"], job="eval", command="python -m eval tables", seed=0)
    assert data["environment"]["options"]["pairs"] == 1 and data["environment"]["options"]["size"] == [48, 160]
    assert len(data["cvc12"]) == 4 and len(data["carla"]) == 6
    for row in data["cvc12"]:
        assert {"scenario", "speed", "e_A", "e_E", "e_U", "e_V", "n_pixels", "paper_e_A", "paper_e_E"} <= set(row)
        assert row["n_pixels"] > 0 and row["e_E"] < 0.01  # exact planes: the fit reproduces the flow
    for row in data["carla"]:
        assert {"direction", "roll_deg", "e_A", "e_E", "roll_abs_error_deg", "paper_e_E"} <= set(row)
        assert row["roll_abs_error_deg"] < 0.01
    assert (out / "tables.md").read_text().startswith("# Freespace model")
    text = capsys.readouterr().out
    assert "paper e_E" in text and "CVC12-like" in text and "CARLA-like" in text


def test_tables_kitti_json_path(tmp_path, shared_data, check_environment):
    path = tmp_path / "k.json"
    rc = main(["tables", "--only", "kitti", "--kitti", str(shared_data / "kitti15_000000"),
               "--out", str(tmp_path / "o"), "--json", str(path), "--no-progress"])
    assert rc == 0
    data = json.loads(path.read_text())
    # no synthetic table: no synthetic settings recorded
    assert data["settings"] == {"kitti": str(shared_data / "kitti15_000000")}
    check_environment(data["environment"], job="eval", command="python -m eval tables", seed=None)
    assert [r["model"] for r in data["kitti"]] == ["paper model", "with pitch"]
    paper, pitch = data["kitti"]
    assert paper["e_E"] <= 0.40 and pitch["e_E"] <= paper["e_E"] + 1e-9
    assert {"e_A", "e_U", "e_V", "n_pixels", "paper_straight"} <= set(paper)


def test_tables_kitti_fl_printed_in_percent(tmp_path, shared_data, capsys):
    """The KITTI table printed Fl, KITTI's headline figure, as a fraction to 4 decimals: 0.0005 and
    0.0008, one significant digit. Printed in percent (as KITTI and the train job print it) with
    its unit in the header, table and Markdown alike; the JSON keeps flow_metrics' fraction.
    Every e_A header has its unit."""
    rc = main(["tables", "--only", "kitti", "--kitti", str(shared_data / "kitti15_000000"),
               "--out", str(tmp_path / "o"), "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0
    rows = json.loads((tmp_path / "o" / "tables.json").read_text())["kitti"]
    md = (tmp_path / "o" / "tables.md").read_text()
    header = next(line for line in out.splitlines() if line.strip().startswith("model"))
    assert "Fl %" in header and "| Fl % |" in md
    for row in rows:
        assert 0 < row["Fl"] < 0.01
        cell = f"{100 * row['Fl']:.3f}"
        assert len(cell.lstrip("0.")) >= 2  # two significant digits at least
        line = next(line for line in out.splitlines() if line.strip().startswith(row["model"]))
        assert cell in line.split() and f"| {cell} |" in md
    from eval.tables import CARLA_COLUMNS, CVC_COLUMNS, KITTI_COLUMNS

    assert all(h == "e_A rad" for cols in (CVC_COLUMNS, CARLA_COLUMNS, KITTI_COLUMNS) for k, h, *_ in cols if k == "e_A")


def test_tables_pairs_end_at_the_renderers_last_frame(tmp_path, capsys, monkeypatch):
    """--pairs past the renderer's frames (MAX_FRAME) exits 2 before any table is made (it used to
    end in a traceback from the renderer after 100 000 pairs of work)."""
    from eval import tables

    for name in ("cvc12_table", "carla_table"):
        monkeypatch.setattr(tables, name, lambda *a, **k: pytest.fail("a table ran with --pairs past MAX_FRAME"))
    assert main(["tables", "--pairs", "100001", "--no-kitti", "--out", str(tmp_path / "t"), "--no-progress"]) == 2
    assert "error: --pairs: expected 1 to 100000, got 100001" in capsys.readouterr().err


def test_tables_bad_arguments(tmp_path, capsys):
    assert main(["tables", "--pairs", "0", "--out", str(tmp_path)]) == 2
    assert "--pairs" in capsys.readouterr().err
    assert main(["tables", "--only", "nope"]) == 2  # (argparse's error: returned, not raised)
    assert "argument --only: invalid choice: 'nope'" in capsys.readouterr().err
    # a KITTI sample asked for but absent: an error, not an empty table
    assert main(["tables", "--kitti", str(tmp_path / "none"), "--out", str(tmp_path), "--no-progress"]) == 2
    assert f"--kitti: no KITTI sample (flow_noc_10.png) at {str(tmp_path / 'none')!r}" in capsys.readouterr().err
    assert not (tmp_path / "tables.json").exists()


def test_paper_figures_and_formatting():
    assert PAPER_CVC12[("complex", 4)] == (0.030, 0.244)
    assert PAPER_CARLA[("turning", -10)] == (0.037, 1.325)
    rows = [{"a": "x", "b": 1.23456}, {"a": "yy", "b": None}]
    cols = [("a", "name", "s"), ("b", "value", ".2f")]
    assert format_table(rows, cols).splitlines()[2].split() == ["x", "1.23"]
    assert markdown_table(rows, cols).splitlines()[3] == "| yy | - |"


def _kitti_copy(tmp_path, shared_data, road=None):
    import shutil

    folder = tmp_path / "k"
    folder.mkdir()
    for name in ("flow_noc_10.png", "calib_cam_to_cam.txt", "road.json"):
        shutil.copy(shared_data / "kitti15_000000" / name, folder / name)
    if road is not None:
        (folder / "road.json").write_text(road)
    return folder


@pytest.mark.parametrize("road, remove, message", [
    ('{"size": [375, 1242]}', None, "has no 'road_polygon'"),
    ('{"size": [375, 1242], "polygons": 5}', None, "expected a list of polygons"),
    (None, "calib_cam_to_cam.txt", "calib_cam_to_cam.txt"),
    (None, "road.json", "road.json"),
    (None, "road.json.folder", "road.json' is a folder"),
    (None, "calib_cam_to_cam.txt.folder", "calib_cam_to_cam.txt' is a folder"),
    ('{"size": [375, 1242], "road_polygon": [[0, 0], [100, 0], [100, 20]]}', None, "covers no pixel with valid"),
])
def test_tables_kitti_files_checked_before_the_synthetic_tables(tmp_path, shared_data, capsys, road, remove, message):
    folder = _kitti_copy(tmp_path, shared_data, road)
    if remove:
        (folder / remove.removesuffix(".folder")).unlink()
        if remove.endswith(".folder"):  # a folder where the file belongs: was an IsADirectoryError traceback
            (folder / remove.removesuffix(".folder")).mkdir()
    rc = main(["tables", "--quick", "--size", "32", "64", "--kitti", str(folder), "--out", str(tmp_path / "o"),
               "--no-progress"])
    captured = capsys.readouterr()
    assert rc == 2 and "error: --kitti: " in captured.err and message in captured.err
    assert "CVC12-like" not in captured.out and not (tmp_path / "o").exists()


def test_tables_kitti_flow_of_another_size_than_the_calibration_exits_2(tmp_path, shared_data, capsys):
    """A flow cropped from the calibrated 375x1242 was fitted with the calibration's principal point
    (the pitch moved from 0.04 to -0.36 degrees), silently: exit 2 naming --kitti and both sizes."""
    import cv2

    folder = _kitti_copy(tmp_path, shared_data)
    flow = cv2.imread(str(folder / "flow_noc_10.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(folder / "flow_noc_10.png"), flow[5:, 16:])
    rc = main(["tables", "--only", "kitti", "--kitti", str(folder), "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and (f"error: --kitti: {str(folder / 'flow_noc_10.png')!r} is 370x1226, but "
                        f"{str(folder / 'calib_cam_to_cam.txt')!r} is for 375x1242 images (S_rect_02)") in err, err
    assert not (tmp_path / "o").exists()


def test_tables_kitti_road_drawn_for_another_size_exits_2(tmp_path, shared_data, capsys):
    """A road.json whose 'size' is not the flow's was stretched over it: with a polygon drawn for
    750x2484 the table printed e_E 8.76 px and a roll of -36.6 degrees with exit 0. Exit 2 naming
    --kitti, road.json and both sizes."""
    import json as json_module

    folder = _kitti_copy(tmp_path, shared_data)
    road = json_module.loads((folder / "road.json").read_text())
    (folder / "road.json").write_text(json_module.dumps({**road, "size": [750, 2484]}))
    rc = main(["tables", "--only", "kitti", "--kitti", str(folder), "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and (f"error: --kitti: {str(folder / 'road.json')!r} is a polygon drawn for 750x2484 images "
                        f"(its 'size'), but size is 375x1242") in err, err
    assert not (tmp_path / "o").exists()


def test_tables_output_paths_checked_first(tmp_path, capsys):
    (tmp_path / "afile").write_text("")
    assert main(["tables", "--quick", "--no-kitti", "--out", str(tmp_path / "afile"), "--no-progress"]) == 2
    assert "error: --out: " in capsys.readouterr().err
    rc = main(["tables", "--quick", "--no-kitti", "--out", str(tmp_path / "o"),
               "--json", str(tmp_path / "afile" / "t.json"), "--no-progress"])
    captured = capsys.readouterr()
    assert rc == 2 and "error: --json: " in captured.err and "CVC12-like" not in captured.out


def test_tables_no_pixels_print_a_dash_not_zeros(capsys):
    from eval.tables import CVC_COLUMNS, _finish, _merge

    def metrics(value, n):
        return {**dict.fromkeys(("e_A", "e_E", "e_U", "e_V", "Fl"), value), "n_pixels": n}

    row = {"scenario": "simple", "speed": "x1", **_finish(_merge(None, metrics(0.0, 0)), "CVC12-like simple x1")}
    assert row["e_E"] is None and row["n_pixels"] == 0
    assert "warning: CVC12-like simple x1: no road pixel" in capsys.readouterr().err
    cells = format_table([row], CVC_COLUMNS).splitlines()[2].split()
    assert cells[2] == "-" and cells[4] == "-"
    assert _finish(_merge(None, metrics(0.5, 4)), "x")["e_E"] == 0.5


@pytest.mark.parametrize("argv, message", [
    # no table left to make: refused, not a tables.md without a table
    (["--only", "kitti", "--no-kitti"], "--no-kitti: not with --only, which names the tables to make (--only kitti)"),
    (["--only", "cvc12", "--no-kitti"], "--no-kitti: not with --only"),
    # a --kitti folder the run would not read: refused, even where it holds no sample
    (["--only", "cvc12", "--kitti", "{tmp}/none"],
     "--kitti: applies to the KITTI table, which this run does not make (--only cvc12)"),
    (["--only", "cvc12", "--only", "carla", "--kitti", "{tmp}"], "(--only cvc12 --only carla)"),
    (["--no-kitti", "--kitti", "{tmp}/none"], "--kitti: applies to the KITTI table, which --no-kitti skips"),
])
def test_tables_options_that_do_not_apply_exit_2(tmp_path, capsys, monkeypatch, argv, message):
    import eval.tables as tables

    for table in ("cvc12_table", "carla_table", "kitti_table"):
        monkeypatch.setattr(tables, table, lambda *a, **k: pytest.fail("a table was made"))
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert main(["tables", "--quick", *argv, "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --") and message in err
    assert not (tmp_path / "o").exists()


def test_tables_default_kitti_folder_given_explicitly_counts_as_asked_for(tmp_path, capsys, monkeypatch):
    """--kitti naming the default folder is a folder asked for: without the sample it exits 2,
    where the default left implicit is skipped with a note."""
    import eval.tables as tables

    monkeypatch.setattr(tables, "DEFAULT_KITTI", tmp_path / "none")
    monkeypatch.setattr(tables, "cvc12_table", lambda *a, **k: [])
    monkeypatch.setattr(tables, "carla_table", lambda *a, **k: [])
    assert main(["tables", "--quick", "--kitti", str(tmp_path / "none"), "--out", str(tmp_path / "o"),
                 "--no-progress"]) == 2
    assert "error: --kitti: no KITTI sample" in capsys.readouterr().err
    assert main(["tables", "--quick", "--out", str(tmp_path / "o"), "--no-progress"]) == 0
    assert "note: no KITTI sample at" in capsys.readouterr().err


@pytest.mark.parametrize("argv, option", [
    (["--size", "20", "20"], "--size"), (["--pairs", "7"], "--pairs"), (["--seed", "5"], "--seed"),
    (["--seed", "0"], "--seed"),  # (its default, given)
    (["--pairs", "3"], "--pairs"), (["--quick"], "--quick"),
])
def test_tables_synthetic_options_without_a_synthetic_table_exit_2(tmp_path, capsys, monkeypatch, argv, option):
    """--size, --pairs, --seed and --quick set the synthetic tables only: given to a run of the
    KITTI table alone they are refused (they were ignored and recorded as the run's settings)."""
    import eval.tables as tables

    monkeypatch.setattr(tables, "load_kitti", lambda *a, **k: pytest.fail("the sample was read"))
    rc = main(["tables", "--only", "kitti", *argv, "--out", str(tmp_path / "o"), "--no-progress"])
    assert rc == 2
    assert (f"error: {option}: applies to the synthetic tables (cvc12, carla), which this run does not make "
            f"(--only kitti)") in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_tables_synthetic_options_with_a_synthetic_table(tmp_path, monkeypatch):
    """With a synthetic table the same options are taken and recorded; the defaults too."""
    import eval.tables as tables

    calls = []
    monkeypatch.setattr(tables, "cvc12_table", lambda *a, **k: calls.append(a[:3]) or [])
    assert main(["tables", "--only", "cvc12", "--size", "20", "24", "--pairs", "2", "--seed", "5",
                 "--out", str(tmp_path / "o"), "--no-progress"]) == 0
    assert main(["tables", "--only", "cvc12", "--out", str(tmp_path / "d"), "--no-progress"]) == 0
    assert calls == [((20, 24), 2, 5), ((375, 1242), 3, 0)]
    settings = json.loads((tmp_path / "o" / "tables.json").read_text())["settings"]
    assert settings == {"size": [20, 24], "pairs": 2, "seed": 5, "quick": False, "rolls_deg": [0, 5, -5, 10, -10],
                        "kitti": None}


@pytest.mark.parametrize("name", ["tables.md", "sub/../tables.md"])
def test_tables_json_naming_tables_md_exits_2(tmp_path, capsys, monkeypatch, name):
    """--json naming DIR/tables.md is refused: one file would replace the other."""
    import eval.tables as tables

    monkeypatch.setattr(tables, "cvc12_table", lambda *a, **k: pytest.fail("a table was made"))
    target = tmp_path / "o" / name
    rc = main(["tables", "--quick", "--only", "cvc12", "--out", str(tmp_path / "o"), "--json", str(target),
               "--no-progress"])
    assert rc == 2
    assert f"error: --json: {str(target)!r} names tables.md, a file the job writes into " in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("size", [["16385", "64"], ["64", "100000000"]])
def test_tables_size_bounded(tmp_path, capsys, monkeypatch, size):
    import eval.tables as tables

    monkeypatch.setattr(tables, "cvc12_table", lambda *a, **k: pytest.fail("a table was made"))
    rc = main(["tables", "--only", "cvc12", "--size", *size, "--out", str(tmp_path / "o"), "--no-progress"])
    assert rc == 2
    assert f"error: --size: expected H, W <= 16384, got [{size[0]}, {size[1]}]" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv, code, stream, message", [
    ([], 2, "err", "python -m eval: error: missing SUBCOMMAND; choose from synth, train, tables, noise, vflow"),
    (["nope"], 2, "err", "python -m eval: error: unknown subcommand 'nope'"),
    (["synth", "--out", "x", "--pairs", "x"], 2, "err", "argument --pairs: invalid int value: 'x'"),
    (["tables", "--bogus"], 2, "err", "unrecognized arguments: --bogus"),
    (["--help"], 0, "out", "SUBCOMMAND"),
    (["tables", "--help"], 0, "out", "--only"),
])
def test_main_returns_the_exit_status(capsys, argv, code, stream, message):
    """main(argv) -> int returns the status, as refine's main does: for a missing or unknown
    subcommand, argparse's errors and --help too (they raised SystemExit)."""
    assert main(argv) == code
    captured = capsys.readouterr()
    assert message in getattr(captured, stream)
    if code:
        assert captured.err.startswith("usage: python -m eval")


@pytest.mark.parametrize("command", ["synth", "train", "tables", "noise", "vflow"])
def test_ctrl_c_prints_one_line_and_exits_130(capsys, monkeypatch, command):
    """A KeyboardInterrupt (Ctrl-C) in any subcommand: one line on stderr naming it, no traceback,
    exit status 130 (as refine's; it raised through main with a traceback)."""
    import importlib

    from eval.__main__ import SUBCOMMANDS

    module = importlib.import_module(SUBCOMMANDS[command][0])

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(module, "run", interrupted)
    argv = {"synth": ["--out", "o"], "vflow": ["--out", "o"]}.get(command, [])
    assert main([command, *argv]) == 130
    err = capsys.readouterr().err
    assert err == f"eval {command}: interrupted; the files written so far are kept, each one whole\n", err


def test_ctrl_c_while_synth_renders_keeps_the_pairs_written(tmp_path, capsys, monkeypatch):
    """Ctrl-C while the second pair renders: exit 130 and one line; the first pair's files are
    whole and no temporary file is left."""
    import fsof_torch.data.scene as scene

    render = scene.render_pair
    calls = []

    def interrupts(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return render(*args, **kwargs)

    monkeypatch.setattr(scene, "render_pair", interrupts)
    out = tmp_path / "o"
    assert main(["synth", "--out", str(out), "--pairs", "3", "--size", "32", "64", "--no-progress"]) == 130
    err = capsys.readouterr().err
    assert err == "eval synth: interrupted; the files written so far are kept, each one whole\n", err
    files = sorted(p for p in out.rglob("*") if p.is_file())
    assert files and all(".tmp" not in p.name and p.stat().st_size > 0 for p in files), files


@pytest.mark.parametrize("name", ["road.json", "flow_noc_10.png", "calib_cam_to_cam.txt"])
def test_tables_json_naming_a_kitti_file_exits_2(tmp_path, shared_data, capsys, name):
    """--json naming a file of the --kitti sample that the KITTI table reads is refused before any
    work, and the file is left as it was (the JSON, written last, replaced road.json)."""
    folder = _kitti_copy(tmp_path, shared_data)
    before = (folder / name).read_bytes()
    rc = main(["tables", "--only", "kitti", "--kitti", str(folder), "--out", str(tmp_path / "o"),
               "--json", str(folder / name), "--no-progress"])
    assert rc == 2
    assert f"error: --json: {str(folder / name)!r} is the input --kitti ({name}); give another path" \
        in capsys.readouterr().err
    assert (folder / name).read_bytes() == before and not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", ["image_10.png", "new.json"])
def test_tables_json_inside_the_kitti_folder_exits_2(tmp_path, shared_data, capsys, name):
    """--json naming any other path inside the --kitti folder (its images, a new file) is refused
    before any work, the folder left as it was (was: the sample's image replaced by the JSON)."""
    import shutil

    folder = _kitti_copy(tmp_path, shared_data)
    shutil.copy(shared_data / "kitti15_000000" / "image_10.png", folder / "image_10.png")
    before = sorted((p.name, p.read_bytes()) for p in folder.iterdir())
    rc = main(["tables", "--only", "kitti", "--kitti", str(folder), "--out", str(tmp_path / "o"),
               "--json", str(folder / name), "--no-progress"])
    assert rc == 2
    assert f"error: --json: {str(folder / name)!r} is inside the input --kitti {str(folder)!r}; give another path" \
        in capsys.readouterr().err
    assert sorted((p.name, p.read_bytes()) for p in folder.iterdir()) == before and not (tmp_path / "o").exists()


def test_tables_rerun_leaves_no_file_of_the_run_before(tmp_path, monkeypatch):
    """A rerun into the same folder that writes its JSON elsewhere removes DIR/tables.json of the
    run before, which would read as this run's beside the new tables.md."""
    import eval.tables as tables

    monkeypatch.setattr(tables, "cvc12_table", lambda *a, **k: [])
    monkeypatch.setattr(tables, "carla_table", lambda *a, **k: [])
    out = tmp_path / "o"
    assert main(["tables", "--only", "cvc12", "--pairs", "1", "--out", str(out), "--no-progress"]) == 0
    assert json.loads((out / "tables.json").read_text())["settings"]["pairs"] == 1
    assert main(["tables", "--only", "carla", "--pairs", "2", "--out", str(out), "--json", str(tmp_path / "t.json"),
                 "--no-progress"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["tables.md"]
    assert "CARLA-like" in (out / "tables.md").read_text()
    assert json.loads((tmp_path / "t.json").read_text())["settings"]["pairs"] == 2


def test_tables_quick_keeps_a_size_and_pairs_given(tmp_path, monkeypatch):
    """--quick with --size or --pairs: the values given replace the quick ones (as documented),
    and the JSON records what ran."""
    import eval.tables as tables

    calls = []
    monkeypatch.setattr(tables, "cvc12_table", lambda *a, **k: calls.append(a[:3]) or [])
    assert main(["tables", "--only", "cvc12", "--quick", "--size", "32", "96", "--out", str(tmp_path / "o"),
                 "--no-progress"]) == 0
    assert main(["tables", "--only", "cvc12", "--quick", "--pairs", "2", "--out", str(tmp_path / "p"),
                 "--no-progress"]) == 0
    assert calls == [((32, 96), 1, 0), ((96, 320), 2, 0)]
    settings = json.loads((tmp_path / "o" / "tables.json").read_text())["settings"]
    assert settings["size"] == [32, 96] and settings["pairs"] == 1 and settings["quick"]


def test_tables_a_run_that_stops_leaves_no_earlier_json(tmp_path, interrupted):
    """An earlier run's --json (elsewhere than --out) goes once the options are checked, as
    DIR/tables.json does: a run stopped during the tables left it to be read as its own."""
    from eval import tables

    path = tmp_path / "elsewhere" / "t.json"
    path.parent.mkdir()
    path.write_text('{"settings": "an earlier run"}')

    interrupted(tables, "cvc12_table", lambda: main(["tables", "--only", "cvc12", "--quick", "--out", str(tmp_path / "t"),
                                                    "--json", str(path), "--no-progress"]))
    assert not path.exists()


@pytest.mark.parametrize("only", [["--only", "cvc12"], ["--only", "carla"], ["--no-kitti"]])
def test_tables_progress_bar_counts_every_fit_once(tmp_path, monkeypatch, only):
    """The bar's total is the number of fits the tables make, so that it ends at 100 % (it
    counted each CVC12-like fit twice: a run ended at 44/56)."""
    import fsof_torch.io.progress as progress

    bars = []
    real = progress.progress_bar

    def recording(*args, **kwargs):
        bar = real(*args, **kwargs)
        bars.append(bar)
        return bar

    monkeypatch.setattr(progress, "progress_bar", recording)
    assert main(["tables", "--quick", "--size", "48", "160", "--pairs", "2", *only, "--out", str(tmp_path / "o")]) == 0
    assert len(bars) == 1 and bars[0].total > 0
    assert bars[0].n == bars[0].total
