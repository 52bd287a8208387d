"""Run folders: --overwrite removes only what planetref wrote; locks; run identity.

Each test names the command it stands for; they run RunDir directly where the command
would take minutes (georef), and the real CLI where it is quick.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from reliability_helpers import REPO, one_line_error, run_cli, run_subprocess

from planetref.errors import RunDirError
from planetref.pipeline.rundir import LOCK_NAME, MARKER, RunDir
from planetref.runtime.atomic import write_json_atomic


def _foreign_tool_folder(root: Path) -> Path:
    """A user's folder holding another tool's run.json, a thesis and a sub-folder."""
    folder = root / "mine"
    (folder / "sub").mkdir(parents=True)
    (folder / "run.json").write_text('{"tool": "snakemake", "jobs": 4}\n')
    (folder / "thesis.txt").write_text("three years of work")
    (folder / "sub" / "data.csv").write_text("1,2,3\n")
    return folder


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != LOCK_NAME
    }


def test_overwrite_refuses_another_tools_folder(tmp_path: Path) -> None:
    # planetref georef SCENE --out mine --overwrite (RunDir is what georef claims)
    folder = _foreign_tool_folder(tmp_path)
    before = _snapshot(folder)
    with pytest.raises(RunDirError, match="not written by planetref"):
        RunDir(folder, "georef", {"matcher": "sift"}, overwrite=True)
    assert _snapshot(folder) == before and not (folder / LOCK_NAME).exists()


def test_simulate_overwrite_refuses_a_foreign_folder(tmp_path: Path) -> None:
    # planetref simulate mine --preset tiny --overwrite
    folder = _foreign_tool_folder(tmp_path)
    before = _snapshot(folder)
    r = run_cli("simulate", folder, "--preset", "tiny", "--overwrite")
    one_line_error(r, str(folder), "not written by planetref")
    assert _snapshot(folder) == before


def test_adjust_overwrite_refuses_a_foreign_folder(tmp_path: Path) -> None:
    # planetref adjust network.toml --out mine --overwrite
    net = REPO.parent / "shared" / "data" / "ctx_syrtis" / "network.toml"
    if not net.is_file():
        pytest.skip("../shared/data/ctx_syrtis is absent")
    folder = _foreign_tool_folder(tmp_path)
    (folder / "run.json").unlink()  # a plain user folder, no run.json at all
    before = _snapshot(folder)
    r = run_cli("adjust", net, "--out", folder, "--overwrite", "--no-plots", "--no-rpc")
    one_line_error(r, str(folder), "not written by planetref")
    assert _snapshot(folder) == before


def test_overwrite_removes_only_listed_files(tmp_path: Path) -> None:
    # planetref georef SCENE --matcher ncc --out run --overwrite, over a sift run
    out = tmp_path / "run"
    run = RunDir(out, "georef", {"matcher": "sift"})
    with run.logging_to_file():
        write_json_atomic(run.file("report.json"), {"ncp": 3})
        run.file("strip1", "tiles.jsonl").write_text('{"tile": 0}\n')
        write_json_atomic(out / "strip1" / "adjustment" / "report.json", {"rmse": 1})
    manifest = json.loads((out / MARKER).read_text())
    assert manifest["format"] == "planetref-run" and manifest["format_version"] == 1
    assert manifest["written_by"].startswith("planetref ")
    assert {"report.json", "strip1/tiles.jsonl", "strip1/adjustment/report.json"} <= set(
        manifest["files"]
    )
    # The user adds notes, at the top and inside a folder planetref made.
    (out / "NOTES.txt").write_text("sift looked better")
    (out / "strip1" / "adjustment" / "mine.txt").write_text("keep")
    (out / "sub").mkdir()
    (out / "sub" / "x.txt").write_text("keep too")
    with pytest.raises(RunDirError, match=r"another run \(georef; matcher: 'sift' -> 'ncc'\)"):
        RunDir(out, "georef", {"matcher": "ncc"})
    run2 = RunDir(out, "georef", {"matcher": "ncc"}, overwrite=True)
    run2.finish()
    assert sorted(_snapshot(out)) == [
        "NOTES.txt",
        "run.json",
        "strip1/adjustment/mine.txt",
        "sub/x.txt",
    ]
    assert json.loads((out / MARKER).read_text())["identity"] == {"matcher": "ncc"}


def test_a_run_never_writes_over_a_user_file(tmp_path: Path) -> None:
    # planetref georef ... --out run (resume) after the user saved their own report.md
    out = tmp_path / "run"
    RunDir(out, "georef", {"matcher": "sift"}).finish()
    (out / "report.md").write_text("my own report")
    run = RunDir(out, "georef", {"matcher": "sift"})
    assert run.resumed
    with pytest.raises(RunDirError, match="not written by planetref"):
        run.file("report.md")
    with run.logging_to_file(), pytest.raises(RunDirError, match=r"report\.md"):
        write_json_atomic(out / "report.md", {"x": 1})
    assert (out / "report.md").read_text() == "my own report"


def test_inputs_changed_since_this_run(tmp_path: Path) -> None:
    # planetref georef SCENE ... after the CCD images were replaced
    image = tmp_path / "ccd1.tif"
    image.write_bytes(b"\0" * 1000)
    out = tmp_path / "run"
    RunDir(out, "georef", {"matcher": "sift"}, inputs=[image]).finish()
    again = RunDir(out, "georef", {"matcher": "sift"}, inputs=[image])
    assert again.resumed
    again.finish()
    image.write_bytes(b"\1" * 1000)  # same size, other content
    with pytest.raises(RunDirError) as info:
        RunDir(out, "georef", {"matcher": "sift"}, inputs=[image])
    assert f"inputs changed since this run ({image.resolve()}): rerun with --overwrite" in str(
        info.value
    )
    assert (
        RunDir(out, "georef", {"matcher": "sift"}, inputs=[image], overwrite=True).resumed is False
    )


def test_weights_and_version_are_part_of_the_identity(tmp_path: Path) -> None:
    weights = tmp_path / "w.pth"
    weights.write_bytes(b"a" * 100)
    out = tmp_path / "run"
    RunDir(out, "georef", {"matcher": "disk"}, weights=[weights]).finish()
    weights.write_bytes(b"b" * 100)
    with pytest.raises(RunDirError, match=r"weights changed since this run \(w.pth\)"):
        RunDir(out, "georef", {"matcher": "disk"}, weights=[weights])
    doc = json.loads((out / MARKER).read_text())
    doc["planetref_version"] = "0.0.1"
    (out / MARKER).write_text(json.dumps(doc))
    with pytest.raises(RunDirError, match=r"written by planetref 0.0.1 \(this is "):
        RunDir(out, "georef", {"matcher": "disk"}, weights=[weights])


def test_an_input_inside_the_run_folder_is_refused(tmp_path: Path) -> None:
    # planetref georef scene/ --out scene/ --overwrite would delete the scene
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.toml").write_text("x")
    with pytest.raises(RunDirError, match="holds an input of this command"):
        RunDir(scene, "georef", {}, inputs=[scene / "scene.toml"], overwrite=True)
    assert (scene / "scene.toml").read_text() == "x"


_HOLD = textwrap.dedent(
    """
    import sys
    from planetref.pipeline.rundir import RunDir
    run = RunDir(sys.argv[1], "simulate", {"scene": "held"})
    print("locked", flush=True)
    sys.stdin.readline()
    run.finish()
    """
)


def test_two_processes_cannot_share_a_run_folder(tmp_path: Path) -> None:
    # two `planetref` processes into the same --out: the second is refused with the pid
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLD, str(out)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        r = run_subprocess("simulate", out, "--preset", "tiny", "--overwrite", timeout=120)
        assert r.returncode == 1, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1, lines
        assert f"in use by another planetref process (pid {holder.pid})" in lines[0]
        assert str(out) in lines[0]
        assert json.loads((out / MARKER).read_text())["identity"] == {"scene": "held"}
    finally:
        holder.communicate("\n", timeout=60)
    assert holder.returncode == 0
    # Released: the folder can be claimed again.
    RunDir(out, "simulate", {"scene": "held"}).finish()


_CRASH = textwrap.dedent(
    """
    import os, sys
    from planetref.pipeline.rundir import RunDir
    run = RunDir(sys.argv[1], "georef", {"matcher": "sift"})
    with open(run.file("strip1", "tiles.jsonl"), "w") as fh:
        fh.write('{"tile": 0}\\n{"tile": 1, "st')
    os._exit(9)  # killed half-way: no finish()
    """
)


def test_a_killed_run_is_still_replaceable(tmp_path: Path) -> None:
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    subprocess.run([sys.executable, "-c", _CRASH, str(out)], env=env, timeout=120, check=False)
    assert "strip1/tiles.jsonl" in json.loads((out / MARKER).read_text())["files"]
    RunDir(out, "georef", {"matcher": "ncc"}, overwrite=True).finish()
    assert not (out / "strip1").exists()


def test_failed_start_leaves_no_run_folder(
    mini_scene: Path, tmp_path: Path, no_weight_packages: None
) -> None:
    # planetref georef mini --matcher nosuch --out run, then the corrected command
    out = tmp_path / "run"
    r = run_cli("georef", mini_scene, "--matcher", "nosuch", "--out", out)
    one_line_error(r, "nosuch")
    assert not out.exists()
    empty = tmp_path / "no-weights"
    empty.mkdir()
    r = run_cli(
        "georef", mini_scene, "--matcher", "disk-lightglue", "--weights-dir", empty, "--out", out
    )
    one_line_error(r, "depth-save.pth")
    assert not out.exists()


def test_simulate_overwrite_keeps_user_files(tmp_path: Path) -> None:
    # planetref simulate scene --preset tiny --config mini.toml --overwrite, with NOTES.txt
    from reliability_helpers import MINI_SCENE

    from planetref.cli.simulate import simulate_run
    from planetref.simulate.config import load_config, merge_overrides

    out = tmp_path / "scene"
    cfg = load_config("tiny", merge_overrides(MINI_SCENE, {"seed": 1}))
    simulate_run(cfg, out)
    listed = set(json.loads((out / MARKER).read_text())["files"])
    assert "scene.toml" in listed and "reference/ortho.tif" in listed
    (out / "NOTES.txt").write_text("seed 1 is the hard one")
    (out / "reference" / "mine.txt").write_text("keep")
    r = run_cli("-q", "simulate", out, "--preset", "tiny")
    one_line_error(r, "rerun with --overwrite")
    simulate_run(cfg, out, overwrite=True)
    assert (out / "NOTES.txt").read_text() == "seed 1 is the hard one"
    assert (out / "reference" / "mine.txt").read_text() == "keep"
    assert (out / "scene.toml").is_file()


def test_the_error_line_also_goes_to_the_run_log(tmp_path: Path) -> None:
    # any command failing inside its run: one line on stderr (the CLI) and in planetref.log
    from planetref.errors import MatchingError

    run = RunDir(tmp_path / "run", "georef", {"matcher": "sift"})
    with pytest.raises(MatchingError), run.logging_to_file():
        raise MatchingError("strip strip1: 3 MCPs,\nat least 6 are needed")
    log = (tmp_path / "run" / "planetref.log").read_text().splitlines()
    assert log[-1].endswith(
        "ERROR planetref: run failed: MatchingError: strip strip1: 3 MCPs, at least 6 are needed"
    )
    # and the lock was released with the error
    RunDir(tmp_path / "run", "georef", {"matcher": "sift"}).finish()


def test_an_output_folder_that_cannot_be_created(tmp_path: Path) -> None:
    # planetref simulate notes.txt/scene: the folder cannot be made under a file. One line
    # naming it and why (was "FileNotFoundError: [Errno ...]"), the file left as it was.
    blocker = tmp_path / "notes.txt"
    blocker.write_text("mine")
    r = run_cli("simulate", blocker / "scene", "--preset", "tiny")
    one_line_error(r, str(blocker / "scene"), "cannot create the output folder")
    assert blocker.read_text() == "mine"


def test_a_read_only_file_is_never_replaced(tmp_path: Path) -> None:
    # Every planetref write goes through atomic_path: a file marked read-only for everyone
    # (shared data, an archive) is refused by its mode bits, so even root does not replace it.
    from planetref.errors import OutputError
    from planetref.runtime.atomic import write_bytes_atomic

    target = tmp_path / "archive.tif"
    target.write_bytes(b"original")
    target.chmod(0o444)
    with pytest.raises(OutputError, match="read-only") as info:
        write_bytes_atomic(target, b"new")
    assert str(target) in str(info.value)
    assert target.read_bytes() == b"original" and [p.name for p in tmp_path.iterdir()] == [
        "archive.tif"
    ]
    target.chmod(0o644)
    write_bytes_atomic(target, b"new")
    assert target.read_bytes() == b"new"


def test_adjust_configuration_errors_name_their_source(tmp_path: Path) -> None:
    # planetref adjust network.toml --config my.toml: a bad key in my.toml used to be
    # reported against network.toml; an [adjust] table (as in georef's --config) was
    # refused as "unknown key 'adjust'" instead of being read.
    net = REPO.parent / "shared" / "data" / "ctx_syrtis" / "network.toml"
    if not net.is_file():
        pytest.skip("../shared/data/ctx_syrtis is absent")
    out = tmp_path / "run"
    mine = tmp_path / "my.toml"
    mine.write_text('[adjust.solver]\nlos = "huber"\n')
    r = run_cli("adjust", net, "--out", out, "--config", mine)
    one_line_error(r, f"{mine}: invalid adjustment configuration", "unknown key 'solver.los'")
    r = run_cli("adjust", net, "--out", out, "--tie-sigma", "-5")
    line = one_line_error(r, "invalid option value", "tie_apriori_sigma_m", "-5.0")
    assert str(net) not in line
    r = run_cli("adjust", net, "--out", out, "--set", "solver.loss=3")
    one_line_error(r, "(after --set)", "'solver.loss'")
    assert not out.exists()


def test_a_failed_download_is_not_a_failed_write(tmp_path: Path) -> None:
    # planetref weights download: with no network the error read "cannot write the file
    # (URLError: ... Name or service not known)"; the source failed, not the disk.
    import urllib.error

    from planetref.runtime.atomic import atomic_path

    target = tmp_path / "w.ckpt"
    with pytest.raises(urllib.error.URLError), atomic_path(target):
        raise urllib.error.URLError("Name or service not known")
    assert list(tmp_path.iterdir()) == []  # nothing left behind


def test_one_json_writer_refuses_nan_unless_told_to_write_null(tmp_path: Path) -> None:
    import numpy as np

    doc = {"rmse": float("nan"), "n": np.int64(3), "v": np.array([1.5, np.inf])}
    with pytest.raises(ValueError, match="JSON compliant"):
        write_json_atomic(tmp_path / "camera.json", {"rmse": float("nan")})
    assert not (tmp_path / "camera.json").exists()  # nothing half-written
    write_json_atomic(tmp_path / "report.json", doc, nan_as_null=True)
    assert json.loads((tmp_path / "report.json").read_text()) == {
        "rmse": None,
        "n": 3,
        "v": [1.5, None],
    }
