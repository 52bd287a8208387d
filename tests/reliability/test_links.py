"""Links and names: planetref never follows a link it did not create (issue 35, group 1).

Each case stands for a hostile folder a user (or another program) could leave: the
lock, the tile journal or the log replaced by a link to the user's file, a hard link,
a linked sub-folder, a strip id that is a path component, a read-only output under
``--overwrite``. In every case the user's file keeps its bytes, and the refusal is one
line naming the path.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest
from reliability_helpers import one_line_error, run_cli

from planetref.errors import InputError, OutputError, RunDirError
from planetref.pipeline.rundir import LOCK_NAME, MARKER, RunDir
from planetref.runtime.atomic import write_json_atomic


def _digests(*roots: Path) -> dict[str, str]:
    """sha256 of every regular file under ``roots`` (links are not followed)."""
    out: dict[str, str] = {}
    for root in roots:
        for p in sorted(root.rglob("*")):
            if p.is_file() and not p.is_symlink():
                out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture
def user_files(tmp_path: Path) -> Path:
    """The user's own folder, beside every run folder of the test."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.txt").write_text("three years of work\n")
    (mine / "data.csv").write_text("1,2,3\n")
    return mine


def test_a_lock_that_is_a_symlink_is_refused(tmp_path: Path, user_files: Path) -> None:
    # planetref simulate out --preset tiny, out/.planetref.lock -> ~/thesis.txt
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).symlink_to(user_files / "thesis.txt")
    before = _digests(user_files)
    with pytest.raises(RunDirError, match="symbolic link"):
        RunDir(out, "georef", {"matcher": "sift"})
    r = run_cli("simulate", out, "--preset", "tiny", "--overwrite")
    one_line_error(r, str(out / LOCK_NAME), "symbolic link")
    assert _digests(user_files) == before
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]  # nothing claimed


def test_a_lock_hard_linked_to_a_user_file_is_refused(tmp_path: Path, user_files: Path) -> None:
    # out/.planetref.lock is a second name of ~/thesis.txt: truncating it destroys the thesis
    out = tmp_path / "out"
    out.mkdir()
    os.link(user_files / "thesis.txt", out / LOCK_NAME)
    before = _digests(user_files)
    with pytest.raises(RunDirError, match="2 hard links"):
        RunDir(out, "georef", {"matcher": "sift"})
    assert _digests(user_files) == before


def test_a_journal_symlink_is_not_repaired(tmp_path: Path, user_files: Path) -> None:
    # planetref georef scene --out run (resume), run/strip1/tiles.jsonl -> ~/data.csv
    from planetref.frontend.journal import TileJournal

    out = tmp_path / "run"
    run = RunDir(out, "georef", {"matcher": "sift"})
    run.file("strip1", "tiles.jsonl").write_text("")
    run.finish()
    journal = out / "strip1" / "tiles.jsonl"
    journal.unlink()
    journal.symlink_to(user_files / "data.csv")
    before = _digests(user_files)
    with pytest.raises(RunDirError, match=r"tiles\.jsonl: .*symbolic link"):
        RunDir(out, "georef", {"matcher": "sift"})
    # The journal itself refuses the link too (any caller, not only a run folder's).
    with pytest.raises(OutputError, match="symbolic link"), TileJournal(journal, "d"):
        pass
    assert _digests(user_files) == before


def test_a_journal_hard_link_is_not_appended_to(tmp_path: Path, user_files: Path) -> None:
    from planetref.frontend.journal import TileJournal

    journal = tmp_path / "tiles.jsonl"
    os.link(user_files / "data.csv", journal)
    before = _digests(user_files)
    with pytest.raises(OutputError, match="hard links"), TileJournal(journal, "d"):
        pass
    assert _digests(user_files) == before


def test_a_log_symlink_is_not_appended_to(tmp_path: Path, user_files: Path) -> None:
    # planetref georef ... --out run, run/planetref.log -> ~/thesis.txt
    out = tmp_path / "run"
    RunDir(out, "georef", {"matcher": "sift"}).finish()
    (out / "planetref.log").symlink_to(user_files / "thesis.txt")
    before = _digests(user_files)
    with pytest.raises(RunDirError, match=r"planetref\.log: .*symbolic link"):
        RunDir(out, "georef", {"matcher": "sift"})
    assert _digests(user_files) == before


def test_a_manifest_symlink_is_refused(tmp_path: Path, user_files: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (user_files / "run.json").write_text(json.dumps({"format": "planetref-run"}))
    (out / MARKER).symlink_to(user_files / "run.json")
    before = _digests(user_files)
    with pytest.raises(RunDirError, match="symbolic link"):
        RunDir(out, "georef", {"matcher": "sift"}, overwrite=True)
    assert _digests(user_files) == before


def test_a_linked_sub_folder_is_not_written_through(tmp_path: Path, user_files: Path) -> None:
    # run/strip1 -> ~/mine: the strip's outputs would land among the user's files
    out = tmp_path / "run"
    RunDir(out, "georef", {"matcher": "sift"}).finish()
    (out / "strip1").symlink_to(user_files, target_is_directory=True)
    before = _digests(user_files)
    run = RunDir(out, "georef", {"matcher": "sift"})
    with pytest.raises(RunDirError, match="link"):
        run.file("strip1", "thesis.txt")
    with run.logging_to_file(), pytest.raises(RunDirError, match="link"):
        write_json_atomic(out / "strip1" / "data.csv", {"x": 1})
    assert _digests(user_files) == before
    assert sorted(p.name for p in user_files.iterdir()) == ["data.csv", "thesis.txt"]


def test_path_components_are_not_run_file_names(tmp_path: Path) -> None:
    run = RunDir(tmp_path / "run", "georef", {"matcher": "sift"})
    for parts in (("..",), ("..", "x.json"), (".", "x"), ("a/b",)):
        with pytest.raises(RunDirError, match="path component"):
            run.file(*parts)
    run.finish()


@pytest.mark.parametrize("bad", ["..", ".", ".hidden"])
def test_strip_and_ccd_ids_that_are_path_components(
    mini_scene: Path, tmp_path: Path, user_files: Path, bad: str
) -> None:
    # planetref georef scene --matcher sift --out mine/run, scene.toml with strip id ".."
    from planetref.scene.manifest import load_manifest

    scene = tmp_path / "scene"
    shutil.copytree(mini_scene, scene, ignore=shutil.ignore_patterns("run.json", ".planetref*"))
    text = (scene / "scene.toml").read_text()
    assert 'id = "strip1"' in text and 'name = "ccd1"' in text
    for old, new in (('id = "strip1"', f'id = "{bad}"'), ('name = "ccd1"', f'name = "{bad}"')):
        (scene / "scene.toml").write_text(text.replace(old, new, 1))
        with pytest.raises(InputError, match="pattern"):
            load_manifest(scene / "scene.toml")
    before = _digests(user_files)
    (scene / "scene.toml").write_text(text.replace('id = "strip1"', f'id = "{bad}"', 1))
    r = run_cli("-q", "georef", scene, "--matcher", "sift", "--out", user_files / "run")
    one_line_error(r, "scene.toml")
    assert _digests(user_files) == before
    assert not (user_files / "run").exists()


def test_overwrite_obeys_the_read_only_rule(tmp_path: Path, user_files: Path) -> None:
    # planetref georef scene --matcher ncc --out run --overwrite, over a sift run whose
    # report.json the user made read-only (chmod 444) to keep it
    out = tmp_path / "run"
    run = RunDir(out, "georef", {"matcher": "sift"})
    with run.logging_to_file():
        write_json_atomic(run.file("report.json"), {"ncp": 3})
        write_json_atomic(run.file("strip1", "mcps.json"), {"n": 1})
    (out / "report.json").chmod(0o444)
    before = _digests(out, user_files)
    with pytest.raises(RunDirError, match=r"report\.json is read-only \(mode 444\)"):
        RunDir(out, "georef", {"matcher": "ncc"}, overwrite=True)
    # Nothing removed: not the read-only file, not the others of the run.
    assert _digests(out, user_files) == before
    (out / "report.json").chmod(0o644)
    RunDir(out, "georef", {"matcher": "ncc"}, overwrite=True).finish()
    assert not (out / "report.json").exists() and not (out / "strip1").exists()


def test_open_regular_refuses_fifos_without_blocking(tmp_path: Path) -> None:
    from planetref.runtime.atomic import open_regular

    fifo = tmp_path / "tiles.jsonl"
    os.mkfifo(fifo)
    with pytest.raises(OutputError, match="not a regular file"):
        open_regular(fifo, os.O_RDWR)
    fd = open_regular(tmp_path / "new.txt", os.O_WRONLY | os.O_CREAT)
    os.close(fd)
    assert (tmp_path / "new.txt").is_file()
