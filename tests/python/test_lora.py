"""`moma.DepthModel(..., lora=...)`: LoRA adapters merged at load, on the tiny random-weight
reference network (MOMA_SHARED_DIR/reference/dav2; outputs mean nothing, this checks the merge).

The adapters are written here, in the safetensors layouts that `moma finetune` writes
(crates/moma-depth/src/candle/train/adapter.rs): `blocks.{i}.{target}.lora_A` (r × in) and
`.lora_B` (rows × r), f32, with metadata naming the architecture and the fingerprint of the base
weights (`moma.lora_fingerprint`); format `moma-lora-v2` adds trained non-LoRA tensors (the head)
under their official names and the head they belong to (`head`, `max_depth_m`)."""

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
KEYS = {"q": "attn.qkv.q", "k": "attn.qkv.k", "v": "attn.qkv.v", "proj": "attn.proj",
        "fc1": "mlp.fc1", "fc2": "mlp.fc2"}


def target_shape(t, d, hidden):
    """(in, rows, first row, official weight) of a target's adapted slice (as LoraTarget::shape)."""
    return {
        "q": (d, d, 0, "attn.qkv"),
        "k": (d, d, d, "attn.qkv"),
        "v": (d, d, 2 * d, "attn.qkv"),
        "proj": (d, d, 0, "attn.proj"),
        "fc1": (d, hidden, 0, "mlp.fc1"),
        "fc2": (hidden, d, 0, "mlp.fc2"),
    }[t]


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
            n_in, rows, _, _ = target_shape(t, d, hidden)
            tensors[f"blocks.{i}.{KEYS[t]}.lora_A"] = rng.normal(0, 0.2, (rank, n_in)).astype(np.float32)
            tensors[f"blocks.{i}.{KEYS[t]}.lora_B"] = (b_scale * rng.normal(0, 1, (rows, rank))).astype(np.float32)
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


def numpy_merge(weights, cfg, tensors, rank, alpha, targets, head=None):
    """The base weights with W[rows] += (α/r)·B·A for every adapted slice and the trained head
    tensors replacing the base ones: the merge, written from the adapter format alone."""
    merged = read_safetensors(weights)
    d, hidden = cfg["embed_dim"], cfg["mlp_hidden_dim"]
    for i in range(cfg["depth"]):
        for t in targets:
            _, rows, row0, name = target_shape(t, d, hidden)
            a = tensors[f"blocks.{i}.{KEYS[t]}.lora_A"].astype(np.float64)
            b = tensors[f"blocks.{i}.{KEYS[t]}.lora_B"].astype(np.float64)
            w = merged[f"pretrained.blocks.{i}.{name}.weight"]
            w[row0 : row0 + rows] += (alpha / rank * (b @ a)).astype(np.float32)
    for k, v in (head or {}).items():
        assert merged[k].shape == v.shape, k
        merged[k] = v
    return merged


def trained_head(weights, seed=1):
    """Every DPT head tensor of `weights` moved as training would: w·(1 + 0.2·N(0,1)) + 0.01·N(0,1)."""
    rng = np.random.default_rng(seed)
    base = read_safetensors(weights)
    return {
        k: (v * (1 + 0.2 * rng.normal(0, 1, v.shape)) + 0.01 * rng.normal(0, 1, v.shape)).astype(np.float32)
        for k, v in base.items()
        if k.startswith("depth_head.")
    }


def v2(meta, head_kind="relative", max_depth=None):
    meta = dict(meta, format="moma-lora-v2", head=head_kind)
    if max_depth is not None:
        meta["max_depth_m"] = str(max_depth)
    return meta


def test_every_target_and_a_trained_head_equal_their_merge_done_in_numpy(setup, tmp_path):
    """Issue 23: LoRA on q, k, v, proj, fc1 and fc2 and a trained head (format v2), merged at
    load, give the prediction of the weights merged here in NumPy and loaded without adapter."""
    cfg, weights, fp, rgb, base = setup
    rank, alpha = 2, 3.0
    targets = ("q", "k", "v", "proj", "fc1", "fc2")
    tensors, meta = adapter(cfg, fp, b_scale=0.3, rank=rank, alpha=alpha, targets=targets, seed=5)
    head = trained_head(weights)
    assert len(head) == 64
    path = tmp_path / "v2.safetensors"
    write_safetensors(path, {**tensors, **head}, v2(meta))
    pred = moma.DepthModel(weights, config=cfg, lora=path).predict(rgb)
    merged_path = tmp_path / "merged.safetensors"
    write_safetensors(merged_path, numpy_merge(weights, cfg, tensors, rank, alpha, targets, head))
    want = moma.DepthModel(merged_path, config=cfg).predict(rgb)
    assert np.abs(want - base).max() > 1e-2 * (base.max() - base.min())
    np.testing.assert_allclose(pred, want, rtol=0, atol=1e-4 * (want.max() - want.min()))
    # Each target on its own, and the head alone (LoRA B = 0), so that no part can hide behind
    # another's larger effect.
    for t in targets:
        one, meta1 = adapter(cfg, fp, b_scale=0.3, rank=rank, alpha=alpha, targets=(t,), seed=7)
        p1 = tmp_path / f"{t}.safetensors"
        write_safetensors(p1, one, meta1)
        got = moma.DepthModel(weights, config=cfg, lora=p1).predict(rgb)
        m1 = tmp_path / f"{t}.merged.safetensors"
        write_safetensors(m1, numpy_merge(weights, cfg, one, rank, alpha, (t,)))
        exp = moma.DepthModel(m1, config=cfg).predict(rgb)
        assert np.abs(exp - base).max() > 1e-4 * (base.max() - base.min()), t
        np.testing.assert_allclose(got, exp, rtol=0, atol=1e-4 * (exp.max() - exp.min()), err_msg=t)
    zero, meta0 = adapter(cfg, fp, b_scale=0.0, rank=rank, alpha=alpha)
    ph = tmp_path / "head.safetensors"
    write_safetensors(ph, {**zero, **head}, v2(meta0))
    got = moma.DepthModel(weights, config=cfg, lora=ph).predict(rgb)
    mh = tmp_path / "head.merged.safetensors"
    write_safetensors(mh, numpy_merge(weights, cfg, zero, rank, alpha, ("q", "v"), head))
    np.testing.assert_allclose(got, moma.DepthModel(mh, config=cfg).predict(rgb), rtol=0,
                               atol=1e-4 * (base.max() - base.min()))


def test_wrong_trained_heads_are_refused(setup, tmp_path):
    cfg, weights, fp, _, _ = setup
    tensors, meta = adapter(cfg, fp, b_scale=0.1)
    head = trained_head(weights)
    # A head trained as metric, applied to this relative network.
    path = tmp_path / "metric.safetensors"
    write_safetensors(path, {**tensors, **head}, v2(meta, "metric", 20.0))
    with pytest.raises(moma.MomaFileError, match="metric head"):
        moma.DepthModel(weights, config=cfg, lora=path)
    # A NaN in a head tensor: refused, naming the file and the tensor.
    bad = dict(head)
    bad["depth_head.scratch.output_conv1.weight"] = bad["depth_head.scratch.output_conv1.weight"].copy()
    bad["depth_head.scratch.output_conv1.weight"].flat[3] = np.nan
    path = tmp_path / "nan.safetensors"
    write_safetensors(path, {**tensors, **bad}, v2(meta))
    with pytest.raises(moma.MomaFileError, match=r"nan\.safetensors.*output_conv1\.weight.*non-finite"):
        moma.DepthModel(weights, config=cfg, lora=path)
    # A head tensor of another shape (another head size).
    odd = dict(head)
    odd["depth_head.projects.0.bias"] = np.zeros(3, np.float32)
    path = tmp_path / "shape.safetensors"
    write_safetensors(path, {**tensors, **odd}, v2(meta))
    with pytest.raises(moma.MomaFileError, match="depth_head.projects.0.bias: shape"):
        moma.DepthModel(weights, config=cfg, lora=path)
