"""Weight files: resolution order, checksums, error messages, loading."""

from __future__ import annotations

import hashlib
import shutil

import pytest

from planetref.errors import WeightsError
from planetref.matching import weights as W


@pytest.fixture
def clean_env(monkeypatch):
    monkeypatch.delenv(W.ENV_VAR, raising=False)
    monkeypatch.delenv("TORCH_HOME", raising=False)
    return monkeypatch


def test_table_is_consistent():
    for name, info in W.WEIGHT_FILES.items():
        assert info.name == name
        assert info.url.startswith("https://")
        assert info.licence
        assert info.sha256 is None or len(info.sha256) == 64
    for name in (
        "depth-save.pth",
        "aliked-n16.pth",
        "xfeat.pt",
        "loftr_outdoor.ckpt",
        "checkpoint_liberty_with_aug.pth",
        "doghardnet_v0-1_arxiv-pth",
    ):
        assert name in W.WEIGHT_FILES


def test_resolution_order(tmp_path, clean_env):
    explicit, env, torch_home = tmp_path / "explicit", tmp_path / "env", tmp_path / "torch"
    (explicit / "hub" / "checkpoints").mkdir(parents=True)
    (env / "checkpoints").mkdir(parents=True)
    flat = tmp_path / "flat"
    flat.mkdir()
    clean_env.setenv(W.ENV_VAR, str(env))
    clean_env.setenv("TORCH_HOME", str(torch_home))
    assert W.weights_dir(explicit) == explicit / "hub" / "checkpoints"
    assert W.weights_dir(flat) == flat  # files directly in the directory
    assert W.weights_dir() == env / "checkpoints"  # hub-dir layout
    clean_env.delenv(W.ENV_VAR)
    assert W.weights_dir() == torch_home / "hub" / "checkpoints"
    clean_env.delenv("TORCH_HOME")
    import torch.hub

    assert W.weights_dir() == W.Path(torch.hub.get_dir()) / "checkpoints"


def test_resolution_does_not_touch_torch_hub(tmp_path, clean_env):
    import torch.hub

    before = torch.hub.get_dir()
    W.weights_dir(tmp_path)
    assert torch.hub.get_dir() == before


def test_missing_file_message_names_dir_file_sha_and_url(tmp_path, clean_env, no_weight_packages):
    with pytest.raises(WeightsError) as err:
        W.resolve_weight("xfeat.pt", tmp_path)
    msg = str(err.value)
    assert str(tmp_path) in msg and "xfeat.pt" in msg
    assert W.WEIGHT_FILES["xfeat.pt"].sha256 in msg
    assert W.WEIGHT_FILES["xfeat.pt"].url in msg
    assert "\n" not in msg
    with pytest.raises(WeightsError) as err:
        W.require_weights(["loftr_outdoor.ckpt", "xfeat.pt"], tmp_path)
    msg = str(err.value)
    assert (
        "loftr_outdoor.ckpt" in msg
        and "xfeat.pt" in msg
        and W.WEIGHT_FILES["loftr_outdoor.ckpt"].url in msg
    )
    with pytest.raises(WeightsError, match="unknown weight file"):
        W.resolve_weight("nope.pth", tmp_path)
    assert isinstance(err.value, FileNotFoundError)


def test_corrupted_copy_is_rejected(tmp_path, shared_weights, clean_env):
    src = shared_weights / "hub" / "checkpoints" / "xfeat.pt"
    dst = tmp_path / "xfeat.pt"
    shutil.copyfile(src, dst)
    assert W.resolve_weight("xfeat.pt", tmp_path) == dst.resolve()
    data = bytearray(dst.read_bytes())
    data[1000] ^= 0xFF
    dst.write_bytes(bytes(data))
    with pytest.raises(WeightsError) as err:
        W.resolve_weight("xfeat.pt", tmp_path)
    msg = str(err.value)
    assert str(dst.resolve()) in msg
    assert W.WEIGHT_FILES["xfeat.pt"].sha256 in msg
    assert hashlib.sha256(bytes(data)).hexdigest() in msg
    # explicit opt-out for files known not to be the official ones
    assert W.resolve_weight("xfeat.pt", tmp_path, verify=False) == dst.resolve()
    with pytest.raises(WeightsError, match="cannot be loaded"):
        dst.write_bytes(b"not a checkpoint")
        W.load_checkpoint("xfeat.pt", tmp_path, verify=False)


def test_git_blob_id_is_accepted(tmp_path, monkeypatch):
    payload = b"hello weights"
    blob = hashlib.sha1(b"blob %d\0" % len(payload) + payload).hexdigest()
    info = W.WeightFile(
        "x.bin", "test", "https://example.org/x.bin", "MIT", sha256="0" * 64, git_blob=blob
    )
    monkeypatch.setitem(W.WEIGHT_FILES, "x.bin", info)
    (tmp_path / "x.bin").write_bytes(payload)
    assert W.resolve_weight("x.bin", tmp_path).name == "x.bin"


def test_hash_computed_once_per_file_version(tmp_path, monkeypatch):
    f = tmp_path / "a.bin"
    f.write_bytes(b"abc")
    calls = []
    real = W.hashlib.sha256

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(W.hashlib, "sha256", counting)
    first = W.file_sha256(f)
    assert W.file_sha256(f) == first
    assert len(calls) == 1
    f.write_bytes(b"abcd")  # new size -> new hash
    assert W.file_sha256(f) != first
    assert len(calls) == 2


def test_shared_files_verify_and_load(shared_weights):
    import torch

    ckpt = W.weights_dir(shared_weights)
    for name in ("aliked-n16.pth", "xfeat.pt"):
        assert W.resolve_weight(name, shared_weights) == (ckpt / name).resolve()
        state = W.load_checkpoint(name, shared_weights)
        assert all(isinstance(v, torch.Tensor) for v in state.values())
