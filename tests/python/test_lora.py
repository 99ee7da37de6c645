"""`moma.DepthModel(..., lora=...)`: LoRA adapters merged at load, on the tiny random-weight
reference network (MOMA_SHARED_DIR/reference/dav2; outputs mean nothing, this checks the merge).

The adapters are written here, in the `moma-lora-v1` safetensors layout that `moma finetune`
writes (crates/moma-depth/src/candle/train/adapter.rs): `blocks.{i}.{target}.lora_A` (r × in)
and `.lora_B` (rows × r), f32, with metadata naming the architecture and the fingerprint of the
base weights (`moma.lora_fingerprint`)."""

import json
import struct

import numpy as np
import pytest

import moma
from conftest import shared_dir
from test_depth_model import tiny_config

SHARED = shared_dir()
REF = SHARED / "reference" / "dav2" if SHARED else None
pytestmark = pytest.mark.skipif(
    REF is None or not (REF / "tiny-rel.safetensors").is_file(),
    reason="Depth Anything reference data not found: set MOMA_SHARED_DIR (needs reference/dav2)",
)

NAME = "tiny-rel"
KEYS = {"q": "attn.qkv.q", "v": "attn.qkv.v", "proj": "attn.proj"}


def write_safetensors(path, tensors, metadata=None):
    """A safetensors file: u64 header length, JSON header, little-endian f32 data."""
    header, blobs, offset = {}, [], 0
    for name in sorted(tensors):
        a = np.ascontiguousarray(tensors[name], dtype="<f4")
        b = a.tobytes()
        header[name] = {"dtype": "F32", "shape": list(a.shape), "data_offsets": [offset, offset + len(b)]}
        blobs.append(b)
        offset += len(b)
    if metadata is not None:
        header["__metadata__"] = metadata
    h = json.dumps(header).encode()
    h += b" " * (-len(h) % 8)
    path.write_bytes(struct.pack("<Q", len(h)) + h + b"".join(blobs))


def read_safetensors(path):
    raw = path.read_bytes()
    n = struct.unpack("<Q", raw[:8])[0]
    header = json.loads(raw[8 : 8 + n])
    out = {}
    for name, t in header.items():
        if name == "__metadata__":
            continue
        assert t["dtype"] == "F32", name
        a, b = t["data_offsets"]
        out[name] = np.frombuffer(raw[8 + n + a : 8 + n + b], dtype="<f4").reshape(t["shape"]).copy()
    return out


def adapter(cfg, fingerprint, b_scale, rank=2, alpha=4.0, targets=("q", "v"), seed=0):
    """Matrices and metadata of an adapter; B = b_scale × N(0, 1)."""
    d, depth, hidden = cfg["embed_dim"], cfg["depth"], cfg["mlp_hidden_dim"]
    rng = np.random.default_rng(seed)
    tensors = {}
    for i in range(depth):
        for t in targets:
            tensors[f"blocks.{i}.{KEYS[t]}.lora_A"] = rng.normal(0, 0.2, (rank, d)).astype(np.float32)
            tensors[f"blocks.{i}.{KEYS[t]}.lora_B"] = (b_scale * rng.normal(0, 1, (d, rank))).astype(np.float32)
    meta = {
        "format": "moma-lora-v1", "rank": str(rank), "alpha": str(alpha), "targets": ",".join(targets),
        "dropout": "0", "seed": str(seed), "embed_dim": str(d), "depth": str(depth),
        "mlp_hidden_dim": str(hidden), "base_fingerprint": fingerprint, "settings": "{}",
    }
    return tensors, meta


@pytest.fixture(scope="module")
def setup():
    cfg = tiny_config(NAME)
    weights = REF / f"{NAME}.safetensors"
    fp = moma.lora_fingerprint(weights, config=cfg)
    rgb = moma.read_rgb(REF / "input.png")
    base = moma.DepthModel(weights, config=cfg).predict(rgb)
    return cfg, weights, fp, rgb, base


def test_fingerprint_is_stable_and_names_the_weights(setup):
    cfg, weights, fp, _, _ = setup
    assert len(fp) == 16 and int(fp, 16) >= 0
    assert moma.lora_fingerprint(weights, config=cfg) == fp
    other = moma.lora_fingerprint(REF / "tiny-metric.safetensors", config=tiny_config("tiny-metric"))
    assert other != fp


def test_zero_b_adapter_changes_nothing(setup, tmp_path):
    cfg, weights, fp, rgb, base = setup
    path = tmp_path / "zero.safetensors"
    write_safetensors(path, *adapter(cfg, fp, b_scale=0.0))
    pred = moma.DepthModel(weights, config=cfg, lora=path).predict(rgb)
    np.testing.assert_array_equal(pred, base)


def test_adapter_equals_its_merge_done_in_numpy(setup, tmp_path):
    """Independent expectation: W_qkv[rows of q / v] += (α/r)·B·A, written as plain weights and
    loaded without an adapter, gives the same prediction as the adapter merged at load."""
    cfg, weights, fp, rgb, base = setup
    rank, alpha = 2, 4.0
    tensors, meta = adapter(cfg, fp, b_scale=0.5, rank=rank, alpha=alpha, targets=("q", "v", "proj"))
    path = tmp_path / "a.safetensors"
    write_safetensors(path, tensors, meta)
    pred = moma.DepthModel(weights, config=cfg, lora=path).predict(rgb)
    assert np.abs(pred - base).max() > 1e-3 * (base.max() - base.min())

    merged = read_safetensors(weights)
    d = cfg["embed_dim"]
    for i in range(cfg["depth"]):
        for t, (name, row0) in {"q": ("attn.qkv", 0), "v": ("attn.qkv", 2 * d), "proj": ("attn.proj", 0)}.items():
            a = tensors[f"blocks.{i}.{KEYS[t]}.lora_A"].astype(np.float64)
            b = tensors[f"blocks.{i}.{KEYS[t]}.lora_B"].astype(np.float64)
            w = merged[f"pretrained.blocks.{i}.{name}.weight"]
            w[row0 : row0 + d] += (alpha / rank * (b @ a)).astype(np.float32)
    merged_path = tmp_path / "merged.safetensors"
    write_safetensors(merged_path, merged)
    want = moma.DepthModel(merged_path, config=cfg).predict(rgb)
    np.testing.assert_allclose(pred, want, rtol=0, atol=1e-4 * (want.max() - want.min()))


def test_adapter_for_other_weights_is_refused(setup, tmp_path):
    cfg, weights, _, _, _ = setup
    path = tmp_path / "other.safetensors"
    write_safetensors(path, *adapter(cfg, "0123456789abcdef", b_scale=0.1))
    with pytest.raises(moma.MomaError, match="other base weights"):
        moma.DepthModel(weights, config=cfg, lora=path)
    with pytest.raises(moma.MomaFileError, match="other.safetensors"):
        moma.DepthModel(weights, config=cfg, lora=path)


def test_adapter_for_another_architecture_is_refused(setup, tmp_path):
    cfg, weights, fp, _, _ = setup
    wrong = dict(cfg, embed_dim=32)
    path = tmp_path / "arch.safetensors"
    write_safetensors(path, *adapter(wrong, fp, b_scale=0.1))
    with pytest.raises(moma.MomaError, match="embed_dim"):
        moma.DepthModel(weights, config=cfg, lora=path)


def test_bad_adapter_files(setup, tmp_path):
    cfg, weights, fp, _, _ = setup
    with pytest.raises(moma.MomaFileError, match="missing.safetensors"):
        moma.DepthModel(weights, config=cfg, lora=tmp_path / "missing.safetensors")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"not a safetensors file")
    with pytest.raises(moma.MomaFileError, match="junk.safetensors"):
        moma.DepthModel(weights, config=cfg, lora=junk)
    tensors, meta = adapter(cfg, fp, b_scale=0.1)
    del tensors["blocks.0.attn.qkv.v.lora_B"]
    incomplete = tmp_path / "incomplete.safetensors"
    write_safetensors(incomplete, tensors, meta)
    with pytest.raises(moma.MomaFileError, match="missing tensor blocks.0.attn.qkv.v.lora_B"):
        moma.DepthModel(weights, config=cfg, lora=incomplete)


def test_lora_needs_the_candle_backend(setup, tmp_path):
    cfg, weights, fp, _, _ = setup
    path = tmp_path / "a.safetensors"
    write_safetensors(path, *adapter(cfg, fp, b_scale=0.1))
    with pytest.raises(moma.BackendError, match="LoRA adapters are merged by the candle backend"):
        moma.DepthModel(REF / f"{NAME}.onnx", backend="onnx", lora=path)
